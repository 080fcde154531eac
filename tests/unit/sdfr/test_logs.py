"""The daemon's logs: one line format (or JSON lines) for every logger, and a recurring error
written once a window, with how many were held back."""

from __future__ import annotations

import json
import logging
import re
import threading
from datetime import datetime

import pytest

from sdfr.config.load import from_args, to_args
from sdfr.daemon import logs
from sdfr.daemon.logs import REPEAT_DISTINCT, RepeatFilter
from sdfr.errors import ConfigError


def record(msg: str, *args: object, level: int = logging.ERROR) -> logging.LogRecord:
    return logging.LogRecord("sdfr.x", level, __file__, 1, msg, args, None)


def test_a_flood_of_one_error_is_a_few_lines_a_minute() -> None:
    now = [0.0]
    f = RepeatFilter(window=60.0, clock=lambda: now[0])
    passed = []
    for i in range(1_770_000 // 1000):  # the 1.77 million lines, thinned for speed
        now[0] = i * 0.04
        rec = record("accept failed: %s", f"Too many open files ({i})")
        if f.filter(rec):
            passed.append(rec.getMessage())
    # 70.8 s of errors, 1770 of them: five a window (each says something new); the first of
    # the second window says how many the first held back.
    assert len(passed) == 2 * REPEAT_DISTINCT
    first = passed[REPEAT_DISTINCT]
    assert first.startswith("accept failed: Too many open files")
    assert first.endswith("(1495 more like this in the last 60 s)")
    assert sum("more like this" in line for line in passed) == 1
    # Other messages, levels and loggers are not held back by it.
    assert f.filter(record("another thing"))
    assert f.filter(record("accept failed: %s", "x", level=logging.WARNING))


def test_a_message_that_says_something_new_is_not_held_back_as_a_repeat() -> None:
    """Two addresses taken within a minute are both told; the same line again is held."""
    now = [0.0]
    f = RepeatFilter(window=60.0, clock=lambda: now[0])
    lines = ["addressing: %s is ours", "addressing: %s is ours", "addressing: %s is ours"]
    args = ["10.1.0.4", "10.1.0.9", "10.1.0.9"]
    passed = []
    for msg, arg in zip(lines, args, strict=True):
        now[0] += 1.0
        rec = record(msg, arg, level=logging.INFO)
        if f.filter(rec):
            passed.append(rec.getMessage())
    assert passed == ["addressing: 10.1.0.4 is ours", "addressing: 10.1.0.9 is ours"]


def _isolated_root() -> tuple[list[logging.Handler], int]:
    root = logging.getLogger()
    saved = root.handlers[:], root.level
    root.handlers = []
    return saved


def _restore_root(saved: tuple[list[logging.Handler], int]) -> None:
    root = logging.getLogger()
    for handler in root.handlers:
        handler.close()
    root.handlers, level = saved
    root.setLevel(level)


STAMP = r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}[+-]\d\d:\d\d"


def test_layer_threads_each_log_in_their_format_and_a_restarted_one_starts_afresh(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """--layers threads: one handler for the process, each layer thread's lines in its own
    format; a layer that starts again (a new thread, maybe with the old one's ident) is not
    held back by what its earlier run logged."""
    saved = _isolated_root()
    try:
        logs.setup("sdfrd")
        logs.share_with_threads()
        log = logging.getLogger("sdfr.layer")

        def layer(component: str, fmt: str) -> None:
            logs.setup(component, fmt=fmt)
            log.info("up")

        for _ in range(2):
            t = threading.Thread(target=layer, args=("api", "text"))
            t.start()
            t.join()
        t = threading.Thread(target=layer, args=("discovery", "json"))
        t.start()
        t.join()
        log.info("up")
        err = capsys.readouterr().err.splitlines()
    finally:
        _restore_root(saved)
    assert len(err) == 4, err
    assert re.fullmatch(f"{STAMP} sdfrd\\[api\\] INFO up", err[0]), err
    assert re.fullmatch(f"{STAMP} sdfrd\\[api\\] INFO up", err[1]), err
    assert json.loads(err[2])["component"] == "discovery"
    assert re.fullmatch(f"{STAMP} sdfrd INFO up", err[3]), err


def test_every_logger_has_one_line_format_with_milliseconds(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """The supervisor's, the layers' and the libraries' records alike: TIME COMPONENT LEVEL
    MESSAGE, local time to the millisecond with its UTC offset; a traceback below its line."""
    saved = _isolated_root()
    try:
        logs.setup("api", "debug")
        logging.getLogger("sdfr.api.access").debug("GET /health 200")
        logging.getLogger("sdfr.config.keystore").warning("key %s is %d days old", "k1", 400)
        try:
            raise OSError("disk full")
        except OSError:
            logging.getLogger("sdfrd").exception("saving failed")
        err = capsys.readouterr().err.splitlines()
    finally:
        _restore_root(saved)
    assert re.fullmatch(f"{STAMP} sdfrd\\[api\\] DEBUG GET /health 200", err[0]), err
    assert re.fullmatch(f"{STAMP} sdfrd\\[api\\] WARNING key k1 is 400 days old", err[1]), err
    assert re.fullmatch(f"{STAMP} sdfrd\\[api\\] ERROR saving failed", err[2]), err
    assert err[3] == "Traceback (most recent call last):" and err[-1] == "OSError: disk full"
    # The time is the record's, to the millisecond, in the local zone.
    rec = record("x")
    rec.created = 1764089742.1239
    stamp = logs.LineFormatter("sdfrd").format(rec).split(" ")[0]
    parsed = datetime.fromisoformat(stamp)
    assert abs(parsed.timestamp() - 1764089742.123) < 1e-6 and parsed.utcoffset() is not None


def test_json_lines_carry_time_level_logger_message_and_fields(
    capsys: pytest.CaptureFixture[str],
) -> None:
    saved = _isolated_root()
    try:
        logs.setup("discovery", "info", "json")
        log = logging.getLogger("sdfrd.fleet")
        fields = {"robot": "r2", "event": "appeared", "address": "10.1.0.2"}
        log.info("robot r2 appeared at 10.1.0.2 (first seen)", extra={logs.FIELDS: fields})
        log.info("robot r2 appeared at 10.1.0.2 (first seen)", extra={logs.FIELDS: fields})
        logging.getLogger("sdfrd.discovery").warning('a "quoted"\nmessage')
        logging.getLogger("sdfrd.discovery").debug("not at info")
        try:
            raise ValueError("bad")
        except ValueError:
            logging.getLogger("sdfrd.discovery").exception("failed")
        err = capsys.readouterr().err.splitlines()
    finally:
        _restore_root(saved)
    lines = [json.loads(line) for line in err]  # every line one JSON object
    assert len(lines) == 4, err
    first = lines[0]
    assert {k: first[k] for k in ("level", "component", "logger", "message")} == {
        "level": "info",
        "component": "discovery",
        "logger": "sdfrd.fleet",
        "message": "robot r2 appeared at 10.1.0.2 (first seen)",
    }
    assert {k: first[k] for k in fields} == fields
    assert re.fullmatch(STAMP, first["time"])
    # A fleet change is never held back as a repeat (its own rate bound is FleetLog's).
    assert lines[1] == {**first, "time": lines[1]["time"]}
    assert lines[2]["message"] == 'a "quoted"\nmessage' and lines[2]["level"] == "warning"
    assert lines[3]["exception"].endswith("ValueError: bad")


def test_a_wrong_log_format_is_refused_naming_the_choices() -> None:
    with pytest.raises(ConfigError, match="log_format: must be text or json, got 'xml'"):
        from_args(["--iface", "lo", "--log-format", "xml"])
    cfg = from_args(["--log-format", "json"])
    assert cfg.log_format == "json" and from_args(to_args(cfg)) == cfg
