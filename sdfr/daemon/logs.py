"""Logging for the daemon's processes: one format each, and no message repeated in a flood."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

#: A message (its template, logger and level) repeated within this many seconds is counted, not
#: written again.
REPEAT_WINDOW = 60.0


class RepeatFilter(logging.Filter):
    """Lets the first of a kind of message through, then one a REPEAT_WINDOW at most, saying
    how many were held back: an error that recurs on every datagram or every accept (a full
    disk, no file descriptors left) must not fill the disk with the log."""

    def __init__(self, window: float = REPEAT_WINDOW, clock: Callable[[], float] = time.monotonic):
        super().__init__()
        self.window = window
        self.clock = clock
        self._seen: dict[tuple[str, int, str], tuple[float, int]] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        key = (record.name, record.levelno, str(record.msg))
        now = self.clock()
        last = self._seen.get(key)
        if last is not None and now - last[0] < self.window:
            self._seen[key] = (last[0], last[1] + 1)
            return False
        if last is not None and last[1]:
            record.msg = f"{record.msg} ({last[1]} more like this in the last {self.window:.0f} s)"
        if len(self._seen) > 1000:  # forget kinds of message not seen for a while
            self._seen = {k: v for k, v in self._seen.items() if now - v[0] < self.window}
        self._seen[key] = (now, 0)
        return True


def setup(fmt: str, level: str | int = logging.INFO) -> None:
    """Log to stderr in `fmt`, at `level`, through a RepeatFilter."""
    logging.basicConfig(format=fmt, level=level.upper() if isinstance(level, str) else level)
    for handler in logging.getLogger().handlers:
        if not any(isinstance(f, RepeatFilter) for f in handler.filters):
            handler.addFilter(RepeatFilter())
