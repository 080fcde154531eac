"""What the radio tier's tests share (tests/radio): waiting at the slow VM's pace, and what a
robot lists."""

from __future__ import annotations

from collections.abc import Callable

from netlab.lab import Lab
from tests.support.waiting import poll


def wait_until(what: str, ok: Callable[[], bool | str], timeout: float) -> float:
    """Seconds until `ok()` is True, looking every 0.5 s (the VM is slow); fails saying `what`
    (and `ok`'s last answer when it says, as a string, what is not yet)."""
    return poll(what, ok, timeout, step=0.5)


def listed(lab: Lab, robot: str) -> set[str]:
    """The robots `robot`'s sdfrd lists as reachable now."""
    return {str(n["robot_id"]) for n in lab.client(robot).neighbors()}
