"""The daemon's logs: a recurring error is written once a window, with how many were held back."""

from __future__ import annotations

import logging
import threading

import pytest

from sdfr.daemon import logs
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


def test_layer_threads_each_log_in_their_format_and_a_restarted_one_starts_afresh(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """--layers threads: one handler for the process, each layer thread's lines in its own
    format; a layer that starts again (a new thread, maybe with the old one's ident) is not
    held back by what its earlier run logged."""
    root = logging.getLogger()
    saved = root.handlers[:], root.level
    root.handlers = []
    try:
        logs.setup("sup %(message)s")
        logs.share_with_threads()
        log = logging.getLogger("sdfr.layer")

        def layer(fmt: str, text: str) -> None:
            logs.setup(fmt)
            log.info(text)

        for _ in range(2):
            t = threading.Thread(target=layer, args=("[one] %(message)s", "up"))
            t.start()
            t.join()
        t = threading.Thread(target=layer, args=("[two] %(message)s", "up"))
        t.start()
        t.join()
        log.info("up")
        err = capsys.readouterr().err.splitlines()
    finally:
        for handler in root.handlers:
            handler.close()
        root.handlers, level = saved
        root.setLevel(level)
    assert err == ["[one] up", "[one] up", "[two] up", "sup up"]
