"""The discovery layer's status record (sdfr.records.status.DiscoveryStatus): the
parts that come from the protocol core and from the layer's own failures, and where the record
goes (`StatusOut`)."""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import deque
from pathlib import Path
from typing import TYPE_CHECKING

from sdfr.daemon import channel
from sdfr.records import status
from sdfr.store import StateWriteError, Store
from sdfr.wire import MESSAGE_TYPES

if TYPE_CHECKING:
    from sdfr.daemon.unknownkeys import UnknownKeys
    from sdfr.protocol import Core

log = logging.getLogger("sdfrd.discovery")

#: The status file (read by an API layer that has no fresh datagram) is written when what it
#: says changed, and at least this often (seconds): it also proves the state dir writable.
STATUS_FILE_EVERY = 30.0

#: Failures of the layer's callbacks within this many seconds make /health say "failing".
ERROR_WINDOW = 60.0


class Failures:
    """Failures of the layer's callbacks: when each came (those within ERROR_WINDOW), and the
    last one's time and message."""

    def __init__(self) -> None:
        self._times: deque[float] = deque()
        self.last: tuple[float, str] | None = None

    def add(self, now: float, message: str) -> bool:
        """Count a failure; whether its message differs from the last one's."""
        self._times.append(now)
        self.recent(now)
        new = self.last is None or self.last[1] != message
        self.last = (now, message)
        return new

    def recent(self, now: float) -> int:
        """Failures within the last ERROR_WINDOW (older ones are forgotten)."""
        while self._times and self._times[0] < now - ERROR_WINDOW:
            self._times.popleft()
        return len(self._times)

    def signature(self) -> tuple[object, ...]:
        """What changes the status's errors part (besides time passing)."""
        return (len(self._times), self.last)

    def status(self, persistent: str | None) -> status.Errors:
        last = self.last
        return status.Errors(
            recent=self.recent(time.time()),
            last=None if last is None else last[1],
            last_at=None if last is None else last[0],
            persistent=persistent,
        )


def thread_id() -> int | None:
    """The calling thread's id when it is not the process's main thread (a layer thread)."""
    if threading.current_thread() is threading.main_thread():
        return None
    return threading.get_native_id()


def counters(core: Core) -> status.Counters:
    c = core.counters
    return status.Counters(
        datagrams_in={k: c.datagrams_in[k] for k in MESSAGE_TYPES},
        datagrams_out={k: c.datagrams_out[k] for k in MESSAGE_TYPES},
        bytes_in=c.bytes_in,
        bytes_out=c.bytes_out,
        rejects=dict(c.rejects),
        challenges=c.challenges,
        challenges_limited=c.challenges_limited,
        invites=c.invites,
    )


def auth(core: Core, unknown_keys: UnknownKeys, offset: float) -> status.Auth:
    """The keyring in use, what it verified, and the unknown keys heard (`offset` takes the
    core's monotonic times to Unix time)."""
    ring = core.keyring
    return status.Auth(
        mode=ring.mode if ring.keyed else "open",
        primary=ring.primary,
        keys=tuple(sorted(ring.keys)),
        received=dict(core.counters.verified),
        ssdp_interop=core.ssdp_interop,
        unknown=tuple(
            status.UnknownKey(
                s.kid, s.address, s.count, s.first_seen + offset, s.last_seen + offset
            )
            for s in unknown_keys.recent(time.monotonic())
        ),
    )


def conflict(core: Core, offset: float) -> status.Conflict | None:
    """Another sender that claims our robot id, if any."""
    c = core.conflict
    if c is None:
        return None
    return status.Conflict(c.address, c.boot_id, c.last_seen + offset, c.count)


def state_dir(problem: tuple[float, str, str] | None) -> status.StateDir:
    """Whether the state directory can be written (`problem`: when, why and what it said)."""
    if problem is None:
        return status.StateDir()
    return status.StateDir(writable=False, reason=problem[1], error=problem[2])


class StatusOut:
    """Where the status record goes: to the API layer over the channel (a datagram, no disk:
    a full state directory does not look like a dead discovery layer), and to the status file
    when what it says changed; and whether the state directory could be written."""

    def __init__(self, state_dir: Path, store: Store) -> None:
        self.to_api = channel.ToApi(state_dir)
        self.store = store
        #: The last failed write of the state directory (time, reason, message), until one works.
        self.problem: tuple[float, str, str] | None = None
        #: What the status file says (without the heartbeat and counters), and when written.
        self._written: tuple[object, float] | None = None
        #: The layer's status signature when the last whole status was sent.
        self._sent: tuple[object, ...] | None = None

    def due(self, signature: tuple[object, ...]) -> bool:
        """Whether the status is to be written now: what it says changed since it was sent,
        or the file is older than STATUS_FILE_EVERY (or was never written)."""
        written = self._written
        return (
            signature != self._sent
            or written is None
            or time.monotonic() - written[1] >= STATUS_FILE_EVERY
        )

    def send(self, record: dict[str, object], signature: tuple[object, ...]) -> None:
        """`record` to the API layer: a datagram, no disk."""
        self._sent = signature
        self.to_api.send(json.dumps(record, separators=(",", ":")).encode())

    def write(self, record: dict[str, object], signature: tuple[object, ...]) -> None:
        """`record` to the API layer, and to the file when what it says changed (the heartbeat
        and the counters aside) or STATUS_FILE_EVERY has passed: a file is not replaced at
        every tick, which would be the layer's largest idle cost."""
        self.send(record, signature)
        key = {k: v for k, v in record.items() if k not in ("heartbeat", "counters")}
        now = time.monotonic()
        last = self._written
        if last is not None and last[0] == key and now - last[1] < STATUS_FILE_EVERY:
            return
        try:
            self.store.write_status(record)
        except StateWriteError as exc:
            self.failed(exc)
            self._written = None
        else:
            self.problem = None
            self._written = (key, now)

    def failed(self, exc: StateWriteError) -> None:
        """A write of the state dir failed (full, read-only): say so in the status, log it
        once a minute (the log filter), and go on discovering."""
        if self.problem is None or self.problem[1] != exc.reason:
            log.error("%s", exc)
        self.problem = (time.time(), exc.reason, str(exc))

    def recovered(self) -> None:
        """The state dir could be written again: say so at once, not at the next rewrite."""
        self.problem = None
        self._written = None
