"""What a logger says, every message, whatever earlier tests left on the root's handlers."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator


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
