"""What a logger says, every message, whatever earlier tests left on the root's handlers."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator

import pytest


class _Said(logging.Handler):
    def __init__(self, level: int) -> None:
        super().__init__(level)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


@contextlib.contextmanager
def logged(*names: str, level: int = logging.INFO) -> Iterator[list[str]]:
    """The messages of loggers `names` at `level` and above, in order.

    Read on the loggers themselves: an sdfrd started by an earlier test of the session leaves
    its repeat filter on the root's handlers (pytest's among them), which then hold back a
    message seen within the last minute.
    """
    said = _Said(level)
    loggers = [logging.getLogger(name) for name in names]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.addHandler(said)
        logger.setLevel(min(level, logger.getEffectiveLevel()))
    try:
        yield said.messages
    finally:
        for logger, before in zip(loggers, levels, strict=True):
            logger.removeHandler(said)
            logger.setLevel(before)


def keep_daemon_logging(monkeypatch: pytest.MonkeyPatch) -> None:
    """Let a test run sdfrd's supervisor.main in this process without its log set-up (its
    repeat filter, its formats, the root level): that is for a process of its own, and left on
    pytest's handlers it would change later tests."""
    from sdfr.daemon import supervisor

    monkeypatch.setattr(supervisor.logs, "setup", lambda *a, **kw: None)
    monkeypatch.setattr(supervisor.logs, "share_with_threads", lambda: None)
    monkeypatch.setattr(logging.getLogger(), "level", logging.getLogger().level)
