"""What the VM tiers' radio tests share (tests/radio, and the wired comparison in
tests/netem): waiting at the slow VM's pace, what a robot lists, and a bundled scenario run
as these tiers run it, with the figures they print."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from netlab import scenario
from netlab.lab import Lab
from tests.support.waiting import poll


def wait_until(what: str, ok: Callable[[], bool | str], timeout: float) -> float:
    """Seconds until `ok()` is True, looking every 0.5 s (the VM is slow); fails saying `what`
    (and `ok`'s last answer when it says, as a string, what is not yet)."""
    return poll(what, ok, timeout, step=0.5)


def listed(lab: Lab, robot: str) -> set[str]:
    """The robots `robot`'s sdfrd lists as reachable now."""
    return {str(n["robot_id"]) for n in lab.client(robot).neighbors()}


def run(
    name: str, folder: Path, medium: str | None = None, **sdfrd: Any
) -> tuple[scenario.RunResult, dict[str, Any]]:
    """A bundled scenario run as the VM tiers run it (quick, no plots), on `medium` when
    given, with `sdfrd`'s options added; it must pass."""
    sc = scenario.load(scenario.find(name))
    if sdfrd:
        sc = replace(sc, sdfrd={**sc.sdfrd, **sdfrd})
    result = scenario.run(sc, run_dir=folder, quick=True, plots=False, medium=medium)
    on = f" on the {medium} medium" if medium else ""
    assert result.ok, "\n".join([f"scenario {name}{on} {result.status}:", *result.summary()])
    report = json.loads((folder / "report.json").read_text())
    return result, report


def times_line(result: scenario.RunResult) -> str:
    """What each check took."""
    took = [(c.description, c.took) for c in result.checks if c.took is not None]
    return "; ".join(f"{what}: {t:.1f} s" for what, t in took)


def startup_line(result: scenario.RunResult, report: dict[str, Any], joined: bool = True) -> str:
    """Start-up's figures: to healthy (over the air, the WiFi `joined`), then to all listing
    all."""
    steps = report["meta"]["steps"]
    start = steps[0]["end"] - steps[0]["start"]
    listed = next(c for c in result.checks if c.kind in ("lists", "medium"))
    healthy = "healthy (WiFi joined)" if joined else "healthy"
    n = report["meta"]["robots"]
    return f"sdfrd {healthy} on {n} in {start:.1f} s, all list all {listed.took:.1f} s later"
