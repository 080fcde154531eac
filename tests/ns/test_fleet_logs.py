"""A robot's log explains a partition and a merge after the fact: real sdfrd daemons in netlab,
and the lines each writes at info level, with their timestamps, in the text and JSON formats."""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from datetime import datetime

import pytest

from netlab.lab import Lab
from tests.support.waiting import poll

pytestmark = pytest.mark.root

BEACON = 0.5
STAMP = r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}[+-]\d\d:\d\d"


def _fleet_lines(lab: Lab, robot: str) -> list[tuple[datetime, str]]:
    """The fleet-change lines of `robot`'s log, text format: (time, message)."""
    out = []
    for line in lab.robot(robot).log.read_text(errors="replace").splitlines():
        m = re.fullmatch(f"({STAMP}) sdfrd\\[discovery\\] INFO (robot .*)", line)
        if m:
            out.append((datetime.fromisoformat(m[1]), m[2]))
    return out


def _said(lab: Lab, robot: str, pattern: str) -> Callable[[], bool | str]:
    def check() -> bool | str:
        lines = [text for _, text in _fleet_lines(lab, robot)]
        return any(re.fullmatch(pattern, t) for t in lines) or f"{robot}: {lines}"

    return check


def _every_log_says(
    lab: Lab, pairs: list[tuple[str, str]], what: str, pattern: str, within: float
) -> None:
    """Wait until robot a's log has the line `pattern` (with `{b}` for the peer) for each
    (a, b) of `pairs`."""
    for a, b in pairs:
        poll(f"{a} logs {b}{what}", _said(lab, a, pattern.format(b=b)), within)


def test_a_partition_and_merge_is_explained_in_every_robots_log(
    fleet_factory: Callable[..., Lab],
) -> None:
    lab = fleet_factory(4, beacon=BEACON)
    left, right = ["r1", "r2"], ["r3", "r4"]
    everyone = [(a, b) for a in left + right for b in left + right if a != b]
    across = [(a, b) for x, y in ((left, right), (right, left)) for a in x for b in y]
    _every_log_says(lab, everyone, "", "robot {b} appeared at \\S+ \\(first seen\\).*", 10)
    lab.partition([left, right])
    cut = datetime.now().astimezone()
    _every_log_says(
        lab, across, " unreachable", "robot {b} unreachable: silent for .*", 3 * BEACON + 10
    )
    lab.merge()
    _every_log_says(lab, across, " back", "robot {b} came back at \\S+ after .*", BEACON + 10)
    # Each robot's lines are in time order, and say the partition after it began.
    for robot in left + right:
        lines = _fleet_lines(lab, robot)
        times = [t for t, _ in lines]
        assert times == sorted(times), lines
        other = right if robot in left else left
        gone = [t for t, text in lines if re.match(f"robot ({'|'.join(other)}) unreachable", text)]
        assert len(gone) >= 2 and all(t >= cut for t in gone), lines


def test_json_logs_carry_the_fleet_changes_as_fields(fleet_factory: Callable[..., Lab]) -> None:
    lab = fleet_factory(2, beacon=BEACON, options={"log_format": "json"})

    def records() -> list[dict[str, object]]:
        text = lab.robot("r1").log.read_text(errors="replace")
        return [json.loads(line) for line in text.splitlines() if line.startswith("{")]

    def appeared() -> bool | str:
        got = [r for r in records() if r.get("event") == "appeared"]
        return bool(got) or str(records()[-5:])

    poll("r1 logs r2 appearing", appeared, 10)
    lab.stop("r2")
    poll("r1 logs r2 leaving", lambda: any(r.get("event") == "left" for r in records()), 5)
    text = lab.robot("r1").log.read_text(errors="replace")
    # Every line of the daemon is one JSON object (netlab's header lines start with ---).
    ours = [line for line in text.splitlines() if line.strip() and not line.startswith("---")]
    assert all(line.startswith("{") for line in ours), text[-2000:]
    [came] = [r for r in records() if r.get("event") == "appeared"]
    assert came["robot"] == "r2" and came["logger"] == "sdfrd.fleet"
    assert came["component"] == "discovery" and came["level"] == "info"
    assert re.fullmatch(STAMP, str(came["time"])) and str(came["address"]).startswith("10.")
    [left] = [r for r in records() if r.get("event") == "left"]
    assert left["message"] == f"robot r2 left (said byebye) from {came['address']}"
