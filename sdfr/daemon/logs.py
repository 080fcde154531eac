"""Logging for the daemon's processes: one format each, and no message repeated in a flood."""

from __future__ import annotations

import logging
import threading
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
        self._seen: dict[tuple[int | None, str, int, str], tuple[float, int]] = {}

    def forget_thread(self, ident: int) -> None:
        """A layer starts (again) as thread `ident` (which a new thread may reuse): it logs its
        start as a layer restarted as a new process does."""
        self._seen = {k: v for k, v in self._seen.items() if k[0] != ident}

    def filter(self, record: logging.LogRecord) -> bool:
        # Each thread's own (a layer's thread forgets its kinds when it starts: `setup`).
        key = (record.thread, record.name, record.levelno, str(record.msg))
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


class _ByThread(logging.Formatter):
    """One handler for a process whose layers are threads: each thread's records in the format
    its layer set up (`setup`), the others' in the supervisor's."""

    def __init__(self, default: logging.Formatter | None) -> None:
        super().__init__()
        self.default = default or logging.Formatter(logging.BASIC_FORMAT)
        self.by_thread: dict[int | None, logging.Formatter] = {}

    def format(self, record: logging.LogRecord) -> str:
        return self.by_thread.get(record.thread, self.default).format(record)


def share_with_threads() -> None:
    """Let the layers that run as threads of this process each set up their own format."""
    for handler in logging.getLogger().handlers:
        if not isinstance(handler.formatter, _ByThread):
            handler.setFormatter(_ByThread(handler.formatter))


def setup(fmt: str, level: str | int = logging.INFO) -> None:
    """Log to stderr in `fmt`, at `level`, through a RepeatFilter. In a thread of a process
    that shares its log with its threads (`share_with_threads`), only that thread's records
    take `fmt`: the level and the handler are the process's."""
    shared = any(isinstance(h.formatter, _ByThread) for h in logging.getLogger().handlers)
    if shared and threading.current_thread() is not threading.main_thread():
        ident = threading.get_ident()
        for handler in logging.getLogger().handlers:
            if isinstance(handler.formatter, _ByThread):
                handler.formatter.by_thread[ident] = logging.Formatter(fmt)
            for f in handler.filters:
                if isinstance(f, RepeatFilter):
                    f.forget_thread(ident)
        return
    logging.basicConfig(format=fmt, level=level.upper() if isinstance(level, str) else level)
    for handler in logging.getLogger().handlers:
        if not any(isinstance(f, RepeatFilter) for f in handler.filters):
            handler.addFilter(RepeatFilter())
