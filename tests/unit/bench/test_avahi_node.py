"""The Avahi peer's pure parts (`bench.avahi_node`; its fleet test is
tests/ns/test_avahi_node.py): what it reads of `avahi-browse -p`, and that it never shares a
lab with python-zeroconf (one port: their traffic could not be told apart)."""

from __future__ import annotations

import pytest

from bench.avahi_node import TYPE, browse_line, instance, owner, txt, unescape
from bench.peers import chosen


def test_resolved_and_removed_lines_name_a_robot_and_a_service() -> None:
    name = instance("r2", "p3x00ab")
    resolved = f'=;veth0;IPv4;{name};{TYPE};local;r2.local;10.1.0.2;9003;"index=3" "name=p"'
    assert browse_line(resolved + "\n") == ("=", ("r2", "p3x00ab"))
    assert browse_line(f"-;veth0;IPv4;{name};{TYPE};local") == ("-", ("r2", "p3x00ab"))
    # Found but not resolved yet, another type, a stranger's name, a short line: nothing.
    assert browse_line(f"+;veth0;IPv4;{name};{TYPE};local") is None
    assert browse_line(f"-;veth0;IPv4;{name};_http._tcp;local") is None
    assert browse_line(f"-;veth0;IPv4;printer;{TYPE};local") is None
    assert browse_line("=;veth0") is None


def test_an_escaped_name_is_read_back() -> None:
    assert unescape("r2--p1x\\046ab\\059") == "r2--p1x.ab;"
    assert owner(unescape("r1\\045\\045p7x0")) == ("r1", "p7x0")
    assert owner("r1-p7") is None and owner("--p7") is None


def test_attributes_go_in_txt_as_key_value() -> None:
    assert txt({"name": "publisher-1", "rate": "11"}) == ["name=publisher-1", "rate=11"]


def test_avahi_and_python_zeroconf_never_share_a_lab() -> None:
    with pytest.raises(
        ValueError, match="avahi and zeroconf cannot run in one lab: both use udp 5353"
    ):
        chosen(["zeroconf", "avahi"])
