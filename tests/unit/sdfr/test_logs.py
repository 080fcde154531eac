"""The daemon's logs: a recurring error is written once a window, with how many were held back."""

from __future__ import annotations

import logging

from sdfr.daemon.logs import RepeatFilter


def record(msg: str, *args: object, level: int = logging.ERROR) -> logging.LogRecord:
    return logging.LogRecord("sdfr.x", level, __file__, 1, msg, args, None)


def test_a_flood_of_one_error_is_one_line_a_minute() -> None:
    now = [0.0]
    f = RepeatFilter(window=60.0, clock=lambda: now[0])
    passed = []
    for i in range(1_770_000 // 1000):  # the 1.77 million lines, thinned for speed
        now[0] = i * 0.04
        rec = record("accept failed: %s", f"Too many open files ({i})")
        if f.filter(rec):
            passed.append(rec.getMessage())
    # 70.8 s of errors: the first, and one after the window that says how many were held.
    assert len(passed) == 2
    assert "more like this in the last 60 s" in passed[1]
    assert passed[1].startswith("accept failed: Too many open files")
    # Other messages, levels and loggers are not held back by it.
    assert f.filter(record("another thing"))
    assert f.filter(record("accept failed: %s", "x", level=logging.WARNING))
