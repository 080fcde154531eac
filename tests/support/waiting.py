"""Waiting for a condition with a deadline, in tests that drive real daemons."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import pytest

from sdfr.errors import ApiError


def poll(what: str, pred: Callable[[], Any], timeout: float, step: float = 0.02) -> float:
    """Wait until `pred()` is truthy; how long it took, or fail saying what was awaited.

    A predicate may answer a string instead of False: not yet, and why (the failure quotes
    the last one)."""
    start = time.monotonic()
    last: Any = None
    while True:
        try:
            last = pred()
        except ApiError as exc:
            last = exc
        if last and not isinstance(last, Exception | str):
            return time.monotonic() - start
        if time.monotonic() - start > timeout:
            pytest.fail(f"{what}: not within {timeout} s (last: {last!r})")
        time.sleep(step)
