"""A lab checks sdfrd's options as a `Config` before it starts a daemon: a typo is an error
naming the option and the closest one, not a daemon that exits at start."""

from __future__ import annotations

from ipaddress import IPv4Interface
from pathlib import Path

import pytest

from netlab.daemons import DaemonOptionError, check_options
from netlab.lab import Lab
from netlab.robots import Robot


def lab_of_one(tmp_path: Path) -> Lab:
    """A lab (never up: nothing here needs root) that knows one robot, r1."""
    lab = Lab("opts", workdir=tmp_path)
    lab._robots["r1"] = Robot(
        "r1", 0, "nl-opts-r1", "vr1", "02:00:00:00:00:01", IPv4Interface("10.1.0.1/16"),
        tmp_path / "r1",
    )  # fmt: skip
    return lab


def test_a_mistyped_option_is_refused_with_the_closest_one(tmp_path: Path) -> None:
    lab = lab_of_one(tmp_path)
    says = "robot r1: mis_limit: not an sdfrd option \\(did you mean 'miss_limit'\\?\\)"
    with pytest.raises(DaemonOptionError, match=says):
        lab.sdfrd_options("r1", mis_limit=3)
    for call in (lab.start, lab.restart, lab.sdfrd_argv):
        with pytest.raises(DaemonOptionError, match="mis_limit"):
            call("r1", mis_limit=3)
    with pytest.raises(DaemonOptionError, match="mis_limit"):
        lab.start_all(mis_limit=3)


def test_a_value_sdfrd_would_refuse_is_refused_too(tmp_path: Path) -> None:
    lab = lab_of_one(tmp_path)
    with pytest.raises(DaemonOptionError, match=r"beacon_interval: must be 0\.05-3600"):
        lab.sdfrd_options("r1", beacon_interval=0.001)
    with pytest.raises(DaemonOptionError, match="miss_limit: expected int"):
        check_options("r1", {"miss_limit": "three"})
    assert isinstance(DaemonOptionError("x"), ValueError)


def test_good_options_give_the_command_line_as_before(tmp_path: Path) -> None:
    lab = lab_of_one(tmp_path)
    argv = lab.sdfrd_argv("r1", beacon_interval=0.5, key_file=None)
    assert argv[argv.index("--robot-id") :] == [
        "--robot-id", "r1", "--state-dir", str(tmp_path / "r1" / "state"),
        "--addressing", "manual", "--beacon-interval", "0.5",
    ]  # fmt: skip
