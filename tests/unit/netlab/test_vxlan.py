"""netlab.vxlan's plan of a medium across hosts, and the medium's rules for robots behind
the VXLAN port (the kernel's side: tests/ns/test_span.py)."""

from __future__ import annotations

import pytest

from netlab import vxlan
from netlab.errors import NetlabError
from netlab.medium import ruleset
from netlab.vxlan import Span, span_of


def test_a_hosts_span_floods_to_every_other_host_and_leaves_room_for_the_header() -> None:
    span = span_of("lab1", "10.0.0.2", ["10.0.0.1", "10.0.0.2", "10.0.0.3"], vni=7)
    assert span.peers == ("10.0.0.1", "10.0.0.3")
    assert span.mtu == 1450
    assert span.create_argv("vx0") == [
        "ip", "link", "add", "vx0", "mtu", "1450", "type", "vxlan",
        "id", "7", "local", "10.0.0.2", "dstport", "4789",
    ]  # fmt: skip
    assert span.flood_argvs("vx0") == [
        ["bridge", "fdb", "append", "00:00:00:00:00:00", "dev", "vx0", "dst", "10.0.0.1"],
        ["bridge", "fdb", "append", "00:00:00:00:00:00", "dev", "vx0", "dst", "10.0.0.3"],
    ]
    assert vxlan.vni_for("lab1") != vxlan.vni_for("lab2")
    assert 1 <= vxlan.vni_for("lab1") < 2**24
    assert span_of("lab1", "10.0.0.2", ["10.0.0.2"]).vni == vxlan.vni_for("lab1")


@pytest.mark.parametrize(
    ("kw", "said"),
    [
        ({"vni": 0}, r"a VNI is 1 to 16777215, got 0"),
        ({"port": 70000}, r"a UDP port is 1 to 65535, got 70000"),
        ({"local": "10.0.0.300"}, r"VXLAN local address: not an IPv4 address: '10.0.0.300'"),
        ({"peers": ("h2",)}, r"VXLAN peer: not an IPv4 address: 'h2'"),
        ({"peers": ("10.0.0.1",)}, r"10.0.0.1 is this host's own address, not a peer"),
        ({"underlay_mtu": 1300}, r"MTU 1300 leaves the robots 1250 .* at least 1330 is needed"),
    ],
)
def test_a_bad_span_is_refused_saying_what_was_wrong(kw: dict[str, object], said: str) -> None:
    base: dict[str, object] = {"vni": 1, "local": "10.0.0.1", "peers": ("10.0.0.2",)}
    with pytest.raises(NetlabError, match=said):
        Span(**{**base, **kw})  # type: ignore[arg-type]


def test_robots_behind_the_span_are_judged_by_mac_on_the_receiving_host_only() -> None:
    links = {("a", "b"): 0.0, ("b", "a"): 25.0, ("c", "a"): 0.0, ("a", "c"): 0.0, ("c", "d"): 0.0}
    ports = {"a": "va", "b": "vb"}
    remote = {"c": "02:00:00:00:00:0c", "d": "02:00:00:00:00:0d"}
    text = ruleset(links, ports, remote=remote, span_port="vx0")
    assert '02:00:00:00:00:0c . "va" : accept,' in text  # c -> a: judged here
    assert '"va" . "vb" : accept,' in text and '"vb" . "va" : jump loss_2500,' in text
    assert "0d" not in text  # c -> d: both remote, their host's business
    assert '"vc"' not in text  # a -> c: passes through vx0, judged on c's host
    forward = text[text.index("chain forward") :]
    assert (
        forward.index('iifname "vx0" ether saddr . oifname vmap @remote')
        < forward.index('oifname "vx0" accept')
        < forward.index("iifname . oifname vmap @pairs")
    )
    assert ruleset(links, ports, remote=remote) == ruleset(
        {k: v for k, v in links.items() if "c" not in k and "d" not in k}, ports
    )  # not spanned: the remote robots are simply absent
