"""The API layer's state: the discovery layer's status, cached views of the store, the
writer of local registrations, and the latency histogram."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import time
from bisect import bisect_left
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sdfr import wire
from sdfr.api.http import AppKey, Request, Response
from sdfr.api.replies import Handler, json_bytes
from sdfr.config.load import Config, location_max_len
from sdfr.daemon.channel import EVENTS, STATUS, notify_discovery
from sdfr.host import procfs
from sdfr.records.model import PeerRecord, Service
from sdfr.records.status import DiscoveryStatus
from sdfr.store import (
    Lease,
    Op,
    Renew,
    Store,
    StoreError,
    write_error,
)

log = logging.getLogger("sdfr.api")


#: A status older than this means the discovery layer is down (seconds). The discovery layer
#: sends its status when it changes and when asked: a request that shows it asks first.
HEARTBEAT_STALE = 5.0
#: A status older than this is asked for again before an answer shows it (seconds).
COUNTERS_FRESH = 0.5
#: The longest such an answer waits for the discovery layer's status (seconds) while the one
#: it has still says "up" (only its counters would be older)...
STATUS_WAIT = 0.25
#: ... and while it would say "down" (a busy discovery layer is not called down too soon).
LIVENESS_WAIT = 2.0
#: Upper bounds (seconds) of the API latency histogram's buckets.
LATENCY_BUCKETS = (
    0.0001,
    0.00025,
    0.0005,
    0.001,
    0.0025,
    0.005,
    0.01,
    0.025,
    0.05,
    0.1,
    0.25,
    0.5,
    1.0,
)


#: Callback failures of the discovery layer within a minute that make /health say "failing".
FAILING_AFTER = 3


# -- discovery status --------------------------------------------------------------------------


def pid_alive(pid: int) -> bool:
    """True when `pid` runs and is not a zombie."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except PermissionError:
        pass  # it exists, under another user
    except OSError:
        return False
    fields = procfs.stat_fields(pid)
    # (No procfs: kill(0) is all there is to know.)
    return fields is None or not fields or fields[0] != "Z"


@dataclass(frozen=True, slots=True)
class DiscoveryState:
    """The discovery layer as its last status record shows it (None: there is none)."""

    up: bool
    heartbeat_age: float | None
    status: DiscoveryStatus | None


def discovery_state(status: DiscoveryStatus | None, now: float | None = None) -> DiscoveryState:
    """Up iff the status's pid (and its thread, if it names one) is alive and its heartbeat
    is younger than HEARTBEAT_STALE."""
    if status is None:
        return DiscoveryState(up=False, heartbeat_age=None, status=None)
    age = round((time.time() if now is None else now) - status.heartbeat, 3)
    up = age < HEARTBEAT_STALE and pid_alive(status.pid)
    if up and status.thread is not None:
        up = procfs.thread_running(status.pid, status.thread)
    return DiscoveryState(up=up, heartbeat_age=age, status=status)


# -- cached views of the store -----------------------------------------------------------------


def neighbor_json(peer: PeerRecord, services: Iterable[Service]) -> dict[str, object]:
    return {
        "robot_id": peer.robot_id,
        "address": peer.address,
        "reachable": peer.reachable,
        "indicator": peer.indicator,
        "rtt_ms": peer.rtt_ms,
        "last_seen": peer.last_seen,
        "services": [s.to_json() for s in services],
    }


def local_json(service: Service, lease: Lease | None) -> dict[str, object]:
    """A registration of this robot: the service, and its lease's ttl and end (or nulls)."""
    return {
        **service.to_json(),
        "ttl": None if lease is None else lease.ttl,
        "expires": None if lease is None else lease.expires,
    }


class StoreView:
    """Reads of the store, cached until the data they come from changes."""

    def __init__(self, store: Store, cfg: Config | None = None) -> None:
        self.store = store
        # What sizes this robot's Update headers: its id, the longest LOCATION it can have.
        self._robot_id = None if cfg is None else cfg.robot_id
        self._location_len = wire.MAX_LOCATION if cfg is None else location_max_len(cfg.describe)
        self._peers_key: int | None = None
        self._peers: list[PeerRecord] = []
        self._peer_bodies: dict[str, bytes] = {}
        self._local_version = -1  # versions start at 0: the first read loads
        self._local: list[Service] = []
        self._local_body: bytes | None = None
        self._sizes: dict[str, int] = {}  # service id -> its JSON size (ids are never reused)
        #: Publishes that passed the parts check and are not stored yet (a slow disk's fsync
        #: runs in a thread: others are checked meanwhile and must count them).
        self._reserved: dict[object, tuple[str, int]] = {}  # -> (service id, JSON size)

    def peers(self) -> list[PeerRecord]:
        """The history map. Only other connections write it, so `data_version` validates it."""
        # Read before loading: a commit in between costs one more reload, never staleness.
        key = self.store.data_version()
        if key != self._peers_key:
            peers = self.store.load_peers()
            if peers != self._peers:  # e.g. only the status heartbeat was committed
                self._peers = peers
                self._peer_bodies.clear()
            self._peers_key = key
        return self._peers

    def peers_body(self, name: str, build: Callable[[list[PeerRecord]], Any]) -> bytes:
        """A JSON body computed from the peers, serialised once per change of the peers."""
        peers = self.peers()
        body = self._peer_bodies.get(name)
        if body is None:
            body = self._peer_bodies[name] = json_bytes(build(peers))
        return body

    def local(self) -> tuple[int, list[Service]]:
        """The local registrations and their version."""
        if self.store.local_version() != self._local_version:
            self._local_version, self._local = self.store.local_state()
            self._local_body = None
        return self._local_version, self._local

    def leases_changed(self) -> None:
        """A lease was renewed (the version stays): the body of /services is made again."""
        self._local_body = None

    def parts_with(self, extra: Service) -> int:
        """Update parts the local set, the publishes in flight and `extra` need, with the
        longest headers this robot can send (its id, its longest LOCATION); each service's
        JSON size is computed once."""
        _, services = self.local()
        sizes = self._sizes
        if len(sizes) > 2 * len(services) + 64:  # drop the sizes of services long gone
            sizes = self._sizes = {s.id: sizes[s.id] for s in services if s.id in sizes}
        for s in services:
            if s.id not in sizes:
                sizes[s.id] = wire.service_json_size(s)
        stored = {s.id for s in services} if self._reserved else set()
        pending = [size for sid, size in self._reserved.values() if sid not in stored]
        sizes[extra.id] = wire.service_json_size(extra)  # (`reserving` takes it from here)
        return wire.parts_needed(
            [*(sizes[s.id] for s in services), *pending, sizes[extra.id]],
            robot_id=self._robot_id,
            location_len=self._location_len,
        )

    @contextlib.contextmanager
    def reserving(self, service: Service) -> Iterator[None]:
        """Count `service` (just checked by `parts_with`) in `parts_with` until it is stored
        (or refused)."""
        key = object()
        size = self._sizes.get(service.id)
        self._reserved[key] = (
            service.id,
            wire.service_json_size(service) if size is None else size,
        )
        try:
            yield
        finally:
            del self._reserved[key]

    def services_body(self) -> bytes:
        version, services = self.local()
        if self._local_body is None:
            leases = {x.service_id: x for x in self.store.leases()}
            self._local_body = json_bytes(
                {
                    "services": [local_json(s, leases.get(s.id)) for s in services],
                    "version": version,
                }
            )
        return self._local_body


# -- API latency -------------------------------------------------------------------------------


@dataclass(slots=True)
class _Histogram:
    buckets: list[int] = field(default_factory=lambda: [0] * len(LATENCY_BUCKETS))
    total: float = 0.0
    count: int = 0

    def observe(self, seconds: float) -> None:
        i = bisect_left(LATENCY_BUCKETS, seconds)  # `le` is inclusive
        if i < len(LATENCY_BUCKETS):
            self.buckets[i] += 1
        self.total += seconds
        self.count += 1


class Writer:
    """Commits changes of the local registrations durably: a 2xx that changed or confirmed a
    registration means on disk, and a commit whose fsync failed changed nothing (SQLite makes
    a durable commit visible only once its log is fsynced: `Store.apply(durable=True)`).

    The first request commits at once, in its own task; requests arriving meanwhile go
    together into the next commit (group commit). A durable commit runs inline while the
    disk answers fast (under INLINE_FSYNC on average: a fraction of a millisecond costs the
    event loop less than a trip to a thread), and in a worker thread when it is slow (an SD
    card's fsync can take tens of milliseconds): reads go on meanwhile. Only a batch of plain
    lease renewals is not fsynced: a power cut that loses one takes its owner (a program on
    this robot) down too, and the lease's end is all it changes.
    """

    #: Average durable commit time (seconds) under which they run inline.
    INLINE_FSYNC = 0.001

    def __init__(
        self,
        state_dir: Path,
        committed: Callable[[], None] | None = None,
        open_store: Callable[[Path], Store] = Store,
    ) -> None:
        self.state_dir = state_dir
        #: Called after each commit (the event streams have news).
        self.committed = committed
        self._open_store = open_store
        self._store: Store | None = None
        self._queue: list[tuple[Op, asyncio.Future[int | StoreError | None]]] = []
        self._busy = False
        self.commits = 0  # transactions (so fsyncs) made
        self.fsync_avg = 0.0  # seconds, smoothed

    async def write(self, op: Op) -> int | StoreError | None:
        """Apply `op`; what Store.apply says of it. StateWriteError when nothing could be."""
        fut: asyncio.Future[int | StoreError | None] = asyncio.get_running_loop().create_future()
        self._queue.append((op, fut))
        if not self._busy:
            self._busy = True
            try:
                await self._drain()
            finally:
                self._busy = False
        return await fut

    async def _drain(self) -> None:
        while self._queue:
            batch, self._queue = self._queue, []
            ops = [op for op, _ in batch]
            try:
                store = self._open()
                if all(isinstance(op, Renew) and not op.set_ttl for op in ops):
                    results = store.apply(ops)
                else:
                    t0 = time.perf_counter()
                    if self.fsync_avg < self.INLINE_FSYNC:
                        results = store.apply(ops, durable=True)
                    else:
                        results = await asyncio.to_thread(store.apply, ops, durable=True)
                    self.fsync_avg = 0.9 * self.fsync_avg + 0.1 * (time.perf_counter() - t0)
                self.commits += 1
                if self.committed is not None:
                    self.committed()
            except StoreError as exc:
                for _, fut in batch:
                    if not fut.done():
                        fut.set_exception(exc)
                continue
            for (_, fut), result in zip(batch, results, strict=True):
                if not fut.done():
                    fut.set_result(result)

    def _open(self) -> Store:
        if self._store is None:
            try:
                self._store = self._open_store(self.state_dir)
            except StoreError as exc:  # e.g. the state dir became read-only
                raise write_error(self.state_dir, exc) from None
        return self._store

    def close(self) -> None:
        if self._store is not None:
            self._store.close()
            self._store = None


@dataclass(slots=True)
class ApiState:
    """What the handlers of one application share."""

    def discovery(self) -> DiscoveryState:
        """The discovery layer's latest status: the one it sent over the channel's
        STATUS_SOCKET while that is fresh, else the file it writes (which survives a restart
        of this layer)."""
        self._decode_live()
        live = self.live_status
        if live is not None and time.time() - live.heartbeat < HEARTBEAT_STALE:
            return discovery_state(live)
        return discovery_state(DiscoveryStatus.from_json(self.store.read_status()))

    def _decode_live(self) -> None:
        """Decode the last whole status datagram, if one came since (decoded only when
        needed: asked for, or a heartbeat to apply to it)."""
        if self.live_raw is not None:
            raw, self.live_raw = self.live_raw, None
            try:
                record = DiscoveryStatus.from_json(json.loads(raw))
            except ValueError:
                record = None
            if record is not None:
                self.live_status = record

    def take_status(self, data: bytes) -> None:
        """A datagram from the discovery layer: its status (kept as it came, decoded when
        asked for), or news in the event log."""
        if data == EVENTS:
            if self.hub is not None:
                self.hub.wake()
            return
        self.live_raw = data
        self.live_at = time.monotonic()
        if self.live_came is not None:
            self.live_came.set()

    async def fresh_status(self) -> None:
        """Make the discovery layer's status current before an answer shows it (/health,
        /self, /metrics, /keys): it sends its status by itself only when more than its
        counters changed. If the last one came more than COUNTERS_FRESH ago, ask for one now
        (the channel's STATUS) and wait for it, up to STATUS_WAIT, or LIVENESS_WAIT if the
        last one is too old to say "up". A discovery layer that does not answer leaves
        the last one (and /health says why); one that is not there is not waited for. A
        layer whose last status says it is starting is always asked: it may have started
        since, and a status saying so may be on its way."""
        self._decode_live()
        live = self.live_status
        if time.monotonic() - self.live_at < COUNTERS_FRESH and not (live and live.starting):
            return
        up = live is not None and time.time() - live.heartbeat < HEARTBEAT_STALE
        came = self.live_came = asyncio.Event()
        try:
            if notify_discovery(self.cfg.state_dir, STATUS):  # (else none is listening)
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(came.wait(), STATUS_WAIT if up else LIVENESS_WAIT)
        finally:
            if self.live_came is came:
                self.live_came = None

    cfg: Config
    view: StoreView
    writer: Writer
    latency: dict[tuple[str, str], _Histogram] = field(default_factory=dict)
    hosts: frozenset[str] = frozenset()
    #: The last failed write of the state directory (time, reason, message), until one works.
    write_problem: tuple[float, str, str] | None = None
    live_status: DiscoveryStatus | None = None
    #: The discovery layer's last status datagram, not decoded yet.
    live_raw: bytes | None = None
    #: When the last whole status datagram came (monotonic), and who waits for the next.
    live_at: float = -1e9
    live_came: asyncio.Event | None = None
    #: GET /events (sdfr.api.events.EventHub) and the lease timer (sdfr.api.leases.Leases);
    #: set by create_app.
    hub: Any = None
    leases: Any = None
    #: The token requests from other machines must carry (api_token_file); None: none may.
    remote_token: bytes | None = None

    @property
    def store(self) -> Store:
        return self.view.store


STATE = AppKey("sdfr_state", ApiState)
_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})


def state_of(request: Request) -> ApiState:
    return request.app[STATE]


async def measure(request: Request, handler: Handler) -> Response:
    start = time.perf_counter()
    try:
        return await handler(request)
    finally:
        if request.route is not None:
            key = (request.method, request.route)
        else:  # bound the label sets whatever clients send
            method = request.method if request.method in _METHODS else "OTHER"
            key = (method, "unmatched")
        latency = state_of(request).latency
        hist = latency.get(key)
        if hist is None:
            hist = latency[key] = _Histogram()
        hist.observe(time.perf_counter() - start)
