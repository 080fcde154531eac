"""Logging for the daemon's processes: one line format for every logger (or JSON lines), and
no message repeated in a flood."""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from datetime import datetime

#: A kind of message (its template, logger and level) is written at most REPEAT_DISTINCT times
#: in this many seconds, each time saying something new (its arguments differ); the rest of
#: the window's are counted, not written.
REPEAT_WINDOW = 60.0
REPEAT_DISTINCT = 5
#: The formats of `--log-format`.
FORMATS = ("text", "json")
#: The attribute of a record (`extra={FIELDS: {...}}`) that carries its structured fields: a
#: JSON line has them as keys of its own. A record that has them is let through the
#: RepeatFilter: whoever logs it bounds its rate (the fleet changes' `FleetLog`).
FIELDS = "fields"


class _Kind:
    """A kind of message in its current window: when the window began, the messages let
    through in it, and how many were held back."""

    __slots__ = ("held", "said", "since")

    def __init__(self, since: float, text: str) -> None:
        self.since = since
        self.said = {text}
        self.held = 0


class RepeatFilter(logging.Filter):
    """Lets a kind of message through at most `distinct` times a `window`, each one saying
    something the window's earlier ones did not (an address that changed, another robot);
    the rest are counted, and the first let through after the window says how many were held
    back. An error that recurs on every datagram or every accept (a full disk, no file
    descriptors left), even with a new detail each time, must not fill the disk with the log;
    two different addresses taken within a minute must both be told."""

    def __init__(
        self,
        window: float = REPEAT_WINDOW,
        clock: Callable[[], float] = time.monotonic,
        distinct: int = REPEAT_DISTINCT,
    ):
        super().__init__()
        self.window = window
        self.clock = clock
        self.distinct = distinct
        self._seen: dict[tuple[int | None, str, int, str], _Kind] = {}

    def forget_thread(self, ident: int) -> None:
        """A layer starts (again) as thread `ident` (which a new thread may reuse): it logs its
        start as a layer restarted as a new process does."""
        self._seen = {k: v for k, v in self._seen.items() if k[0] != ident}

    def filter(self, record: logging.LogRecord) -> bool:
        if getattr(record, FIELDS, None) is not None:
            return True
        # Each thread's own (a layer's thread forgets its kinds when it starts: `setup`).
        key = (record.thread, record.name, record.levelno, str(record.msg))
        try:
            text = record.getMessage()
        except Exception:  # (arguments that do not fit: the handler will say so)
            text = str(record.msg)
        now = self.clock()
        kind = self._seen.get(key)
        if kind is not None and now - kind.since < self.window:
            if text in kind.said or len(kind.said) >= self.distinct:
                kind.held += 1
                return False
            kind.said.add(text)
            return True
        if kind is not None and kind.held:
            record.msg = (
                f"{record.msg} ({kind.held} more like this in the last {self.window:.0f} s)"
            )
        if len(self._seen) > 1000:  # forget kinds of message not seen for a while
            self._seen = {k: v for k, v in self._seen.items() if now - v.since < self.window}
        self._seen[key] = _Kind(now, text)
        return True


def timestamp(created: float) -> str:
    """`created` (seconds since the epoch) as local time with milliseconds and the UTC
    offset: 2026-11-25T16:55:42.123+00:00 (RFC 3339; it sorts, and says its zone)."""
    return datetime.fromtimestamp(created).astimezone().isoformat(timespec="milliseconds")


class LineFormatter(logging.Formatter):
    """`TIME COMPONENT LEVEL MESSAGE`, a traceback on the lines below it."""

    def __init__(self, component: str) -> None:
        super().__init__()
        self.component = component
        self.label = component if component == "sdfrd" else f"sdfrd[{component}]"

    def format(self, record: logging.LogRecord) -> str:
        line = f"{timestamp(record.created)} {self.label} {record.levelname} {record.getMessage()}"
        extra = self._details(record)
        return f"{line}\n{extra}" if extra else line

    def _details(self, record: logging.LogRecord) -> str:
        if record.exc_info and not record.exc_text:
            record.exc_text = self.formatException(record.exc_info)
        parts = [p for p in (record.exc_text, record.stack_info) if p]
        return "\n".join(parts)


class JsonFormatter(LineFormatter):
    """One JSON object a line: time, level, component, logger, message, the record's
    structured fields (`FIELDS`), and a traceback as `exception`."""

    def format(self, record: logging.LogRecord) -> str:
        obj: dict[str, object] = {
            "time": timestamp(record.created),
            "level": record.levelname.lower(),
            "component": self.component,
            "logger": record.name,
            "message": record.getMessage(),
        }
        fields = getattr(record, FIELDS, None)
        if isinstance(fields, dict):
            obj.update((k, v) for k, v in fields.items() if k not in obj)
        extra = self._details(record)
        if extra:
            obj["exception"] = extra
        return json.dumps(obj, ensure_ascii=False, separators=(",", ":"), default=str)


def formatter(component: str, fmt: str = "text") -> logging.Formatter:
    """The formatter of `component`'s records (`sdfrd`, `api`, `discovery`) in `fmt`."""
    if fmt not in FORMATS:
        raise ValueError(f"log format must be {' or '.join(FORMATS)}, got {fmt!r}")
    return JsonFormatter(component) if fmt == "json" else LineFormatter(component)


class _ByThread(logging.Formatter):
    """One handler for a process whose layers are threads: each thread's records in the format
    its layer set up (`setup`), the others' in the supervisor's."""

    def __init__(self, default: logging.Formatter | None) -> None:
        super().__init__()
        self.default = default or LineFormatter("sdfrd")
        self.by_thread: dict[int | None, logging.Formatter] = {}

    def format(self, record: logging.LogRecord) -> str:
        return self.by_thread.get(record.thread, self.default).format(record)


class _Handler(logging.StreamHandler):  # type: ignore[type-arg]
    """sdfrd's own handler (to stderr): `setup` may set its format again."""


def share_with_threads() -> None:
    """Let the layers that run as threads of this process each set up their own format."""
    for handler in logging.getLogger().handlers:
        if not isinstance(handler.formatter, _ByThread):
            handler.setFormatter(_ByThread(handler.formatter))


def setup(component: str, level: str | int = logging.INFO, fmt: str = "text") -> None:
    """Log `component`'s records to stderr in `fmt` (text or json), at `level`, through a
    RepeatFilter; called again, set the format and level anew. In a thread of a process
    that shares its log with its threads (`share_with_threads`), only that thread's records
    take the format: the level and the handler are the process's. A process whose root
    logger has handlers of someone else's (a test runner's) keeps them as they are, with a
    RepeatFilter added."""
    form = formatter(component, fmt)
    root = logging.getLogger()
    shared = any(isinstance(h.formatter, _ByThread) for h in root.handlers)
    if shared and threading.current_thread() is not threading.main_thread():
        ident = threading.get_ident()
        for handler in root.handlers:
            if isinstance(handler.formatter, _ByThread):
                handler.formatter.by_thread[ident] = form
            for f in handler.filters:
                if isinstance(f, RepeatFilter):
                    f.forget_thread(ident)
        return
    if not root.handlers:
        root.addHandler(_Handler())
    ours = [h for h in root.handlers if isinstance(h, _Handler)]
    if ours:
        root.setLevel(level.upper() if isinstance(level, str) else level)
    for handler in ours:
        if isinstance(handler.formatter, _ByThread):
            handler.formatter.default = form
        else:
            handler.setFormatter(form)
    for handler in root.handlers:
        if not any(isinstance(f, RepeatFilter) for f in handler.filters):
            handler.addFilter(RepeatFilter())
