"""What the ROS 1 and ROS 2 probes share: a test's client of the `sdfr` node, run inside a
robot under a ROS interpreter, that takes commands as JSON lines on stdin and answers each
with one JSON line on stdout (`{"ok": true, ...}` or `{"ok": false, "error": ...}`).

Messages become plain JSON: fields by name, times as float seconds, NaN as null.
"""

from __future__ import annotations

import json
import math
import sys
import threading
import time
import traceback
from collections.abc import Callable
from typing import Any

_ROS2_TIME = {"sec", "nanosec"}


def to_py(value: Any) -> Any:
    if isinstance(value, bytes):
        return value[0] if len(value) == 1 else list(value)
    if isinstance(value, float):
        return None if math.isnan(value) else value
    if isinstance(value, (str, int, bool)) or value is None:
        return value
    if isinstance(value, (list, tuple)) or type(value).__name__ == "array":
        return [to_py(v) for v in value]
    if hasattr(value, "secs") and hasattr(value, "nsecs"):  # ROS 1 time
        return value.secs + value.nsecs * 1e-9
    if hasattr(value, "get_fields_and_field_types"):  # ROS 2 message
        names = list(value.get_fields_and_field_types())
        if set(names) == _ROS2_TIME:
            return value.sec + value.nanosec * 1e-9
    elif hasattr(value, "_type") and hasattr(value, "__slots__"):  # ROS 1 message (genpy)
        names = list(value.__slots__)
    else:
        return str(value)
    return {n: to_py(getattr(value, n)) for n in names}


class Recorded:
    """Messages of one topic with the time each arrived."""

    def __init__(self) -> None:
        self.items: list[tuple[float, Any]] = []
        self.cond = threading.Condition()

    def add(self, msg: Any) -> None:
        t = time.time()
        item = to_py(msg)
        with self.cond:
            self.items.append((t, item))
            self.cond.notify_all()

    def first(self, pred: Callable[[Any], bool], since: float, timeout: float) -> tuple[float, Any]:
        """The first message after `since` for which `pred` holds (waiting up to `timeout`)."""
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                for t, item in self.items:
                    if t >= since and pred(item):
                        return t, item
                left = deadline - time.monotonic()
                if left <= 0:
                    last = self.items[-1][1] if self.items else None
                    raise TimeoutError(f"no such message within {timeout} s; the last: {last}")
                self.cond.wait(left)


def has_service(robot_id: str, name: str | None, present: bool) -> Callable[[Any], bool]:
    """A NeighborList in which robot `robot_id` is listed (with a service called `name`, if
    given) -- or, not `present`, is not."""

    def pred(nl: Any) -> bool:
        for r in nl["robots"]:
            if r["robot_id"] == robot_id and (
                name is None or any(s["name"] == name for s in r["services"])
            ):
                return present
        return not present

    return pred


def serve(backend: Any) -> None:
    """Answer commands until stdin closes."""
    for line in sys.stdin:
        if not line.strip():
            continue
        try:
            cmd = json.loads(line)
            op = cmd.pop("op")
            reply = getattr(backend, "op_" + op)(**cmd) or {}
            out = {"ok": True, **reply}
        except Exception as exc:
            out = {
                "ok": False,
                "error": f"{type(exc).__name__}: {exc}",
                "trace": traceback.format_exc(),
            }
        sys.stdout.write(json.dumps(out) + "\n")
        sys.stdout.flush()
