"""The API layer's HTTP applications: the local REST API and the read-only description server.

Both answer from the durable store the discovery layer writes (the paper's shared memory),
so they keep answering, from the last known state, while discovery is down. Reads are
cached and revalidated per request with one tiny query: the peers on SQLite's
`data_version` (it changes when another connection, i.e. the discovery layer, commits),
the local registrations on their version (bumped by every publish/unpublish, whichever
connection made it).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import secrets
import socket
import time
from bisect import bisect_left
from collections.abc import Awaitable, Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from aiohttp import web
from aiohttp.http_exceptions import LineTooLong
from aiohttp.web_protocol import RequestHandler
from aiohttp.web_request import BaseRequest

from sdfr import __version__, auth, keystore, procfs, wire
from sdfr.config import Config, location_max_len
from sdfr.errors import ConfigError, ValidationError
from sdfr.keystore import KeyringError, KeyringFileError, StoredKeyring
from sdfr.model import PeerRecord, Service
from sdfr.status import DiscoveryStatus
from sdfr.store import (
    Op,
    StateWriteError,
    Store,
    StoreError,
    write_error,
    write_reason,
)
from sdfr.wire import check_service_fits

log = logging.getLogger("sdfr.api")

#: A heartbeat older than this means the discovery layer is down (it writes one every second).
HEARTBEAT_STALE = 3.0
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
#: A registration is at most one datagram; a request body never needs more than this.
MAX_BODY = 64 * 1024
#: Callback failures of the discovery layer within a minute that make /health say "failing".
FAILING_AFTER = 3
#: Longest a request body may take to arrive (a slow sender holds a connection, no more).
BODY_TIMEOUT = 10.0
#: An idle or half-sent connection is closed after this many seconds (slowloris).
IDLE_TIMEOUT = 15.0
#: Methods whose body, when there is one, must be JSON.
_BODY_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
#: Names the local API always answers to.
_LOCAL_HOSTS = frozenset({"127.0.0.1", "localhost", "::1"})

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


# -- errors and JSON ---------------------------------------------------------------------------


class RequestError(Exception):
    """An error answer other than a validation error (422): status, message, field."""

    def __init__(self, status: int, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.status = status
        self.message = message
        self.field = field


def _json_bytes(obj: Any) -> bytes:
    return json.dumps(obj, ensure_ascii=False, separators=(",", ":"), allow_nan=False).encode()


def _json_response(
    body: Any, status: int = 200, headers: Mapping[str, str] | None = None
) -> web.Response:
    data = body if isinstance(body, bytes) else _json_bytes(body)
    return web.Response(
        body=data, status=status, headers=headers, content_type="application/json", charset="utf-8"
    )


def _error(
    status: int, message: str, field: str | None = None, headers: Mapping[str, str] | None = None
) -> web.Response:
    return _json_response({"error": message, "field": field}, status, headers)


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not valid JSON")


async def _read_json(request: web.Request) -> Any:
    try:
        raw = await asyncio.wait_for(request.read(), BODY_TIMEOUT)
    except TimeoutError:
        raise RequestError(
            408, f"the request body did not arrive within {BODY_TIMEOUT:.0f} s"
        ) from None
    if not raw.strip():
        raise RequestError(400, "the request body is empty; expected a JSON object")
    try:
        # NaN and Infinity are not JSON: accepting them would store values no client can read.
        return json.loads(raw, parse_constant=_reject_constant)
    except UnicodeDecodeError:
        raise RequestError(400, "invalid JSON: the body is not UTF-8") from None
    except ValueError as exc:
        raise RequestError(400, f"invalid JSON: {exc}") from None
    except RecursionError:
        raise RequestError(400, "invalid JSON: nested too deeply") from None


def _http_message(exc: web.HTTPException, request: web.Request) -> str:
    if exc.status == 404:
        return f"no such endpoint: {request.path}"
    if exc.status == 405:
        allowed = exc.headers.get("Allow", "")
        return f"method {request.method} is not allowed on {request.path}; allowed: {allowed}"
    text = (exc.text or "").removeprefix(f"{exc.status}: ")
    return text or exc.reason


@web.middleware
async def _errors_as_json(request: web.Request, handler: Handler) -> web.StreamResponse:
    """Every error, the router's 404/405 included, is `{"error": ..., "field": ...}`."""
    try:
        return await handler(request)
    except ValidationError as exc:
        return _error(422, exc.message, exc.field)
    except (RequestError, KeyringError) as exc:
        return _error(exc.status, exc.message, exc.field)
    except StateWriteError as exc:
        # Nothing was stored: say why, and let /health say it too until a write succeeds.
        _state(request).write_problem = (time.time(), exc.reason, str(exc))
        return _error(_cannot_write_status(exc.reason), str(exc), "state_dir")
    except web.HTTPException as exc:
        if exc.status < 400:
            raise
        drop = ("content-type", "content-length")
        keep = {k: v for k, v in exc.headers.items() if k.lower() not in drop}
        return _error(exc.status, _http_message(exc, request), None, keep)
    except Exception:
        log.exception("%s %s failed", request.method, request.path)
        return _error(500, "internal error; the daemon's log has the details")


def _cannot_write_status(reason: str) -> int:
    """The answer to a write the state directory refused: 507 when it is full, else 503."""
    return 507 if reason == "full" else 503


# -- who may knock -----------------------------------------------------------------------------


def over_unix_socket(request: web.Request) -> bool:
    transport = request.transport
    sock = transport.get_extra_info("socket") if transport is not None else None
    return sock is not None and sock.family == socket.AF_UNIX


def host_name(header: str) -> str:
    """The name or address in a Host header, without its port or brackets, lower case."""
    value = header.strip().lower()
    if value.startswith("["):
        return value[1 : value.find("]")] if "]" in value else value
    name, colon, port = value.rpartition(":")
    return name if colon and port.isdigit() and ":" not in name else value


def allowed_hosts(cfg: Config) -> frozenset[str]:
    api_host = cfg.api.rpartition(":")[0].strip("[]").lower()
    return _LOCAL_HOSTS | {api_host} | {host_name(h) for h in cfg.api_allowed_hosts}


@web.middleware
async def _doors(request: web.Request, handler: Handler) -> web.StreamResponse:
    """The write API is for programs on this robot, not for web pages they happen to show.

    - Host must be one of this API's own names (else a page on a name that resolves to
      127.0.0.1 could read the fleet: DNS rebinding); not checked on the unix socket.
    - A browser's cross-site request (Origin, Sec-Fetch-Site) is refused unless its origin
      is in api_allowed_origins; programs send neither header.
    - A body must be JSON: a form or text/plain body is what a page can send without asking.
    """
    state = _state(request)
    if not over_unix_socket(request):
        host = request.headers.get("Host")
        if host is not None and host_name(host) not in state.hosts:
            raise RequestError(
                403,
                f"Host {host!r} is not a name of this API (allowed: "
                f"{', '.join(sorted(state.hosts))}; add more with api_allowed_hosts)",
                "Host",
            )
    origin = request.headers.get("Origin")
    site = request.headers.get("Sec-Fetch-Site")
    cross = origin is not None or (site is not None and site not in ("same-origin", "none"))
    if cross and origin not in state.cfg.api_allowed_origins:
        raise RequestError(
            403,
            f"a cross-site request from a web page ({origin or site}) is refused; a page may "
            "call the local API only from an origin in api_allowed_origins",
            "Origin",
        )
    if (
        request.method in _BODY_METHODS
        and request.body_exists
        and request.content_type != "application/json"
    ):
        raise RequestError(
            415,
            f"the body must be JSON (Content-Type: application/json), not "
            f"{request.headers.get('Content-Type') or 'untyped'}",
            "Content-Type",
        )
    return await handler(request)


# -- discovery notification --------------------------------------------------------------------


def notify_discovery(state_dir: Path) -> None:
    """Wake the discovery layer so it announces a change of the local services at once.

    Best effort: when discovery is down it is told nothing, and it polls the version anyway.
    """
    path = str(state_dir / "discovery.sock")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.setblocking(False)
        try:
            sock.sendto(b"services\n", path)
        except (FileNotFoundError, ConnectionRefusedError, BlockingIOError):
            pass
        except OSError as exc:
            log.warning("cannot notify the discovery layer at %s: %s", path, exc)


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
    """Up iff the status's pid is alive and its heartbeat is younger than HEARTBEAT_STALE."""
    if status is None:
        return DiscoveryState(up=False, heartbeat_age=None, status=None)
    age = round((time.time() if now is None else now) - status.heartbeat, 3)
    up = age < HEARTBEAT_STALE and pid_alive(status.pid)
    return DiscoveryState(up=up, heartbeat_age=age, status=status)


# -- cached views of the store -----------------------------------------------------------------


def _neighbor_json(peer: PeerRecord, services: Iterable[Service]) -> dict[str, Any]:
    return {
        "robot_id": peer.robot_id,
        "address": peer.address,
        "reachable": peer.reachable,
        "indicator": peer.indicator,
        "rtt_ms": peer.rtt_ms,
        "last_seen": peer.last_seen,
        "services": [s.to_json() for s in services],
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
            body = self._peer_bodies[name] = _json_bytes(build(peers))
        return body

    def local(self) -> tuple[int, list[Service]]:
        """The local registrations and their version."""
        if self.store.local_version() != self._local_version:
            self._local_version, self._local = self.store.local_state()
            self._local_body = None
        return self._local_version, self._local

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
            self._local_body = _json_bytes(
                {"services": [s.to_json() for s in services], "version": version}
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
    """Commits changes of the local registrations durably: a 201 means on disk.

    The first request commits at once, in its own task; requests arriving meanwhile go
    together into the next commit (group commit). The fsync that makes a commit durable runs
    inline while the disk answers fast (under INLINE_FSYNC on average: a fraction of a
    millisecond costs the event loop less than a trip to a thread), and in a worker thread
    when it is slow (an SD card's fsync can take tens of milliseconds): reads go on meanwhile.
    """

    #: Average fsync time (seconds) under which fsyncs run inline.
    INLINE_FSYNC = 0.001

    def __init__(self, state_dir: Path) -> None:
        self.state_dir = state_dir
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
            try:
                store = self._open()
                results = store.apply([op for op, _ in batch])
                t0 = time.perf_counter()
                if self.fsync_avg < self.INLINE_FSYNC:
                    store.sync()
                else:
                    await asyncio.to_thread(store.sync)
                self.fsync_avg = 0.9 * self.fsync_avg + 0.1 * (time.perf_counter() - t0)
                self.commits += 1
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
                self._store = Store(self.state_dir)
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
        """The discovery layer's latest status: the one it sent over STATUS_SOCKET while that
        is fresh, else the file it writes (which survives a restart of this layer)."""
        live = self.live_status
        if live is not None and time.time() - live.heartbeat < HEARTBEAT_STALE:
            return discovery_state(live)
        return discovery_state(DiscoveryStatus.from_json(self.store.read_status()))

    def take_status(self, data: bytes) -> None:
        """A status datagram from the discovery layer."""
        try:
            record = DiscoveryStatus.from_json(json.loads(data))
        except ValueError:
            return
        if record is not None:
            self.live_status = record

    cfg: Config
    view: StoreView
    writer: Writer
    latency: dict[tuple[str, str], _Histogram] = field(default_factory=dict)
    hosts: frozenset[str] = frozenset()
    #: The last failed write of the state directory (time, reason, message), until one works.
    write_problem: tuple[float, str, str] | None = None
    live_status: DiscoveryStatus | None = None

    @property
    def store(self) -> Store:
        return self.view.store


STATE = web.AppKey("sdfr_state", ApiState)
_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})


def _state(request: web.Request) -> ApiState:
    return request.app[STATE]


@web.middleware
async def _measure(request: web.Request, handler: Handler) -> web.StreamResponse:
    start = time.perf_counter()
    try:
        return await handler(request)
    finally:
        resource = request.match_info.route.resource
        if resource is not None:
            key = (request.method, resource.canonical)
        else:  # bound the label sets whatever clients send
            method = request.method if request.method in _METHODS else "OTHER"
            key = (method, "unmatched")
        latency = _state(request).latency
        hist = latency.get(key)
        if hist is None:
            hist = latency[key] = _Histogram()
        hist.observe(time.perf_counter() - start)


# -- handlers: local registrations -------------------------------------------------------------


def _published(service: Service, version: int, status: int) -> web.Response:
    return _json_response(
        {"id": service.id, "service": service.to_json(), "version": version},
        status=status,
        headers={"Location": f"/services/{service.id}"},
    )


def _published_already(state: ApiState, service: Service) -> web.Response | None:
    """A publish under a chosen id that is stored already: the same service again (a client
    retrying after a lost answer) gets 200 and nothing changes; another one, 409."""
    stored = state.store.get_service(service.id)
    if stored is None:
        return None
    if stored != service:
        raise RequestError(
            409,
            f"service id {service.id!r} is taken by another service; choose another id, or "
            "leave id out and the robot picks one",
            "id",
        )
    return _published(stored, state.store.local_version(), 200)


async def publish(request: web.Request) -> web.Response:
    state = _state(request)
    obj = await _read_json(request)
    chosen = isinstance(obj, dict) and "id" in obj
    service = Service.from_json(obj, service_id=None if chosen else secrets.token_hex(6))
    check_service_fits(service)
    if chosen and (again := _published_already(state, service)) is not None:
        return again
    # What the fleet can never see must not be acknowledged: one announcement is at most
    # MAX_PARTS datagrams.
    needed = state.view.parts_with(service)
    if needed > wire.MAX_PARTS:
        raise RequestError(
            507,
            f"this robot's services would need {needed} update parts, more than the "
            f"{wire.MAX_PARTS} one announcement can carry; unpublish some or make them smaller",
            "services",
        )
    with state.view.reserving(service):  # checked: concurrent publishes must count it
        for _ in range(3):
            result = await state.writer.write(("add", service))
            if isinstance(result, int):
                break
            if chosen:  # the same id published by a request that was in flight with this one
                again = _published_already(state, service)
                assert again is not None
                return again
            service = replace(service, id=secrets.token_hex(6))  # the random id exists: another
        else:
            raise RequestError(500, "could not allocate a service id")
    state.write_problem = None
    notify_discovery(state.cfg.state_dir)
    log.info("published %s (%s, %s), version %d", service.id, service.name, service.type, result)
    return _published(service, result, 201)


async def unpublish(request: web.Request) -> web.Response:
    state = _state(request)
    service_id = request.match_info["id"]
    version = await state.writer.write(("remove", service_id))
    if version is None:
        raise RequestError(404, f"no local service with id {service_id!r}", "id")
    state.write_problem = None
    notify_discovery(state.cfg.state_dir)
    log.info("unpublished %s, version %s", service_id, version)
    return web.Response(status=204)


async def list_services(request: web.Request) -> web.Response:
    return _json_response(_state(request).view.services_body())


# -- handlers: what discovery found ------------------------------------------------------------


def _only_params(request: web.Request, allowed: Iterable[str]) -> None:
    known = set(allowed)
    for key in request.query:
        if key not in known:
            hint = ", ".join(sorted(known)) or "none"
            raise ValidationError(key, f"unknown query parameter (known: {hint})")


def _flag(request: web.Request, name: str) -> bool:
    raw = request.query.get(name)
    if raw is None:
        return False
    value = raw.strip().lower()
    if value in ("1", "true", "yes", ""):
        return True
    if value in ("0", "false", "no"):
        return False
    raise ValidationError(name, "must be 1/0, true/false or yes/no")


def _neighbors(peers: list[PeerRecord], include_unreachable: bool) -> dict[str, Any]:
    return {
        "neighbors": [
            _neighbor_json(p, p.services) for p in peers if include_unreachable or p.reachable
        ]
    }


async def neighbors(request: web.Request) -> web.Response:
    _only_params(request, ["all"])
    include_unreachable = _flag(request, "all")
    name = "neighbors.all" if include_unreachable else "neighbors"
    body = _state(request).view.peers_body(
        name, lambda peers: _neighbors(peers, include_unreachable)
    )
    return _json_response(body)


def _search_criteria(request: web.Request) -> tuple[str | None, dict[str, str]]:
    stype: str | None = None
    attrs: dict[str, str] = {}
    for key, value in request.query.items():
        if key == "type":
            if stype is not None:
                raise ValidationError("type", "given more than once")
            if not value:
                raise ValidationError("type", "must not be empty")
            stype = value
        elif key.startswith("attr.") and len(key) > len("attr."):
            name = key[len("attr.") :]
            if name in attrs:
                raise ValidationError(key, "given more than once")
            attrs[name] = value
        else:
            raise ValidationError(
                key, "unknown query parameter (known: type, attr.KEY for any attribute KEY)"
            )
    if stype is None and not attrs:
        raise ValidationError("type", "give at least one criterion: type=T or attr.KEY=VALUE")
    return stype, attrs


async def search(request: web.Request) -> web.Response:
    stype, attrs = _search_criteria(request)
    found = []
    for peer in _state(request).view.peers():
        if not peer.reachable:
            continue
        matching = [s for s in peer.services if s.matches(stype, attrs)]
        if matching:
            found.append(_neighbor_json(peer, matching))
    return _json_response({"neighbors": found})


async def history(request: web.Request) -> web.Response:
    body = _state(request).view.peers_body(
        "history", lambda peers: {"robots": [p.to_json() for p in peers]}
    )
    return _json_response(body)


# -- handlers: this robot ----------------------------------------------------------------------


def _discovery_json(disc: DiscoveryState) -> dict[str, Any]:
    s = disc.status
    return {
        "up": disc.up,
        "heartbeat_age": disc.heartbeat_age,
        "pid": None if s is None else s.pid,
        "iface": None if s is None else s.iface,
        "started": None if s is None else s.started,
        "announced_version": None if s is None else s.version,
        "peers_reachable": None if s is None else s.peers_reachable,
        "peers_known": None if s is None else s.peers_known,
    }


async def self_info(request: web.Request) -> web.Response:
    state = _state(request)
    disc = state.discovery()
    version, services = state.view.local()
    rec = disc.status
    return _json_response(
        {
            "robot_id": state.cfg.robot_id or (None if rec is None else rec.robot_id),
            "fleet": state.cfg.fleet,
            "iface": state.cfg.iface,
            "address": "" if rec is None else rec.address,
            "boot_id": None if rec is None else rec.boot_id,
            "version": version,
            "location": None if rec is None else rec.location,
            "software": f"sdfr/{__version__}",
            "services": [s.to_json() for s in services],
            "discovery": _discovery_json(disc),
        }
    )


def discovery_error(status: DiscoveryStatus) -> str | None:
    """Why the discovery layer, though alive, is failing (None when it is not): its callbacks
    failed FAILING_AFTER times within a minute, or it cannot announce our services."""
    errors = status.errors
    if errors.persistent:
        return errors.persistent
    if errors.recent >= FAILING_AFTER and errors.last is not None:
        return errors.last
    return None


def health_warnings(status: DiscoveryStatus, now: float | None = None) -> list[str]:
    """What an operator should look at while the daemon is up."""
    out = []
    conflict = status.robot_id_conflict
    if conflict is not None:
        ago = max(0.0, (time.time() if now is None else now) - conflict.last_seen)
        out.append(
            f"another sender claims this robot's id {status.robot_id}: {conflict.address} "
            f"(boot {conflict.boot_id}, {ago:.0f} s ago, {conflict.count} datagrams); give "
            "each daemon its own --robot-id"
        )
    mode = status.auth.mode
    if mode in ("accept", "sign"):
        out.append(
            f"keyring mode {mode}: unsigned datagrams are accepted; finish with "
            "`sdfr keys mode enforce` on every robot"
        )
    return out


def state_problem(state: ApiState, disc: DiscoveryState) -> tuple[str, str] | None:
    """Why the state directory cannot be written, if it cannot: (full | read-only | error,
    message), from this layer's last failed write (until one works) or the discovery
    layer's report."""
    if state.write_problem is not None and time.time() - state.write_problem[0] < 60.0:
        return state.write_problem[1], state.write_problem[2]
    report = None if disc.status is None else disc.status.state
    if disc.up and report is not None and not report.writable:
        return report.reason or "error", report.error or ""
    return None


async def health(request: web.Request) -> web.Response:
    state = _state(request)
    disc = state.discovery()
    failing = discovery_error(disc.status) if disc.up and disc.status else None
    warnings = health_warnings(disc.status) if disc.up and disc.status else []
    cannot_write = state_problem(state, disc)
    ok = disc.up and failing is None and cannot_write is None
    return _json_response(
        {
            "status": "degraded" if not ok else "warning" if warnings else "ok",
            "api": "up",
            "discovery": "failing" if failing else "up" if disc.up else "down",
            "discovery_heartbeat_age": disc.heartbeat_age,
            "discovery_error": failing,
            "state": "ok" if cannot_write is None else cannot_write[0],
            "state_error": None if cannot_write is None else cannot_write[1],
            "auth": None if disc.status is None else disc.status.auth.mode,
            "warnings": warnings,
        },
        status=200 if ok else 503,
    )


# -- handlers: the fleet keyring (unix socket only) --------------------------------------------


def _need_unix_socket(request: web.Request) -> None:
    """Key management is for whoever may open STATE_DIR/api.sock (its file mode says who),
    never for any program that can reach a TCP port."""
    if not over_unix_socket(request):
        path = _state(request).cfg.state_dir / "api.sock"
        raise RequestError(
            403,
            f"key management is only available on the unix socket {path} "
            "(sdfr keys --state-dir DIR, or --socket PATH)",
        )


def _keys_json(state: ApiState, stored: StoredKeyring) -> dict[str, Any]:
    ring = stored.keyring
    status = state.discovery().status
    received = {} if status is None else status.auth.received
    return {
        "mode": ring.mode if ring.keyed else "open",
        "primary": ring.primary,
        "keyed": ring.keyed,
        "ssdp_interop": auth.plain_ssdp_answered(state.cfg.ssdp_interop_wanted, ring),
        "keys": [
            {
                "id": kid,
                "primary": kid == ring.primary,
                "installed": stored.installed.get(kid),
                "received": received.get(kid, 0),
            }
            for kid in sorted(ring.keys)
        ],
    }


def _keyring_failed(exc: KeyringFileError) -> RequestError:
    """keyring.json could not be read or written: say so, with the status a state directory
    problem gets elsewhere (507 full, 503 read-only), and 500 for a damaged file."""
    log.warning("%s", exc)
    reason = write_reason(exc.errno)
    status = 500 if reason == "error" else _cannot_write_status(reason)
    return RequestError(status, str(exc), "keyring")


def _load_keyring(state: ApiState) -> StoredKeyring:
    try:
        return keystore.load(state.cfg.state_dir)
    except KeyringFileError as exc:
        raise _keyring_failed(exc) from None


def _save_keyring(state: ApiState, stored: StoredKeyring, what: str) -> None:
    try:
        keystore.save(state.cfg.state_dir, stored)
    except KeyringFileError as exc:
        raise _keyring_failed(exc) from None
    notify_discovery(state.cfg.state_dir)
    ring = stored.keyring
    log.info("keyring: %s; mode %s, signing with %s", what, ring.mode, ring.primary)


async def keys_list(request: web.Request) -> web.Response:
    _need_unix_socket(request)
    state = _state(request)
    return _json_response(_keys_json(state, _load_keyring(state)))


async def _one_text_field(request: web.Request, name: str, shape: str) -> str:
    """The body `{name: "..."}` and nothing else; a 422 naming `name` otherwise."""
    obj = await _read_json(request)
    if not isinstance(obj, dict) or set(obj) != {name} or not isinstance(obj[name], str):
        raise ValidationError(name, f"expected {{{name!r}: {shape}}}".replace("'", '"'))
    value: str = obj[name]
    return value


async def keys_install(request: web.Request) -> web.Response:
    _need_unix_socket(request)
    state = _state(request)
    text = await _one_text_field(request, "key", '"<base64 of 32 bytes>"')
    try:
        key = keystore.parse_key(text, "key")
    except ConfigError as exc:
        raise ValidationError("key", str(exc).removeprefix("key: ")) from None
    stored, added = keystore.install(_load_keyring(state), key, time.time())
    kid = auth.key_id(key)
    if added:
        _save_keyring(state, stored, f"key {kid} installed")
    body = {"id": kid, **_keys_json(state, stored)}
    return _json_response(body, status=201 if added else 200)


async def keys_use(request: web.Request) -> web.Response:
    _need_unix_socket(request)
    state = _state(request)
    kid = request.match_info["id"]
    stored = keystore.use(_load_keyring(state), kid)
    _save_keyring(state, stored, f"signing with key {kid}")
    return _json_response(_keys_json(state, stored))


async def keys_remove(request: web.Request) -> web.Response:
    _need_unix_socket(request)
    state = _state(request)
    kid = request.match_info["id"]
    stored = keystore.remove(_load_keyring(state), kid)
    _save_keyring(state, stored, f"key {kid} removed")
    return web.Response(status=204)


async def keys_mode(request: web.Request) -> web.Response:
    _need_unix_socket(request)
    state = _state(request)
    mode = await _one_text_field(request, "mode", '"accept" | "sign" | "enforce"')
    stored = keystore.set_mode(_load_keyring(state), mode)
    _save_keyring(state, stored, f"mode {mode}")
    return _json_response(_keys_json(state, stored))


# -- /metrics ----------------------------------------------------------------------------------


def _label(value: object) -> str:
    return str(value).replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def metrics_text(state: ApiState) -> str:
    """The Prometheus text exposition (format 0.0.4)."""
    disc = state.discovery()
    status = disc.status or DiscoveryStatus(pid=0, heartbeat=0.0)  # zeros while there is none
    c = status.counters
    peers = state.view.peers()
    _, local = state.view.local()
    out: list[str] = []

    def family(name: str, kind: str, text: str) -> None:
        out.append(f"# HELP {name} {text}")
        out.append(f"# TYPE {name} {kind}")

    family(
        "sdfr_datagrams_total",
        "counter",
        "SDfR datagrams received and sent by the discovery layer, by message type.",
    )
    for direction, by_type in (("in", c.datagrams_in), ("out", c.datagrams_out)):
        for kind in [*wire.MESSAGE_TYPES, *sorted(set(by_type) - set(wire.MESSAGE_TYPES))]:
            out.append(
                f'sdfr_datagrams_total{{direction="{direction}",type="{_label(kind)}"}} '
                f"{by_type.get(kind, 0)}"
            )
    family("sdfr_bytes_total", "counter", "UDP payload bytes received and sent.")
    out.append(f'sdfr_bytes_total{{direction="in"}} {c.bytes_in}')
    out.append(f'sdfr_bytes_total{{direction="out"}} {c.bytes_out}')
    family(
        "sdfr_rejects_total",
        "counter",
        "Datagrams rejected (malformed, foreign, unauthenticated, replayed, refused or "
        "rate-limited), by reason.",
    )
    for reason, count in sorted(c.rejects.items()):
        out.append(f'sdfr_rejects_total{{reason="{_label(reason)}"}} {count}')
    family("sdfr_peers", "gauge", "Robots in the history map: reachable now, and known ever.")
    reachable = sum(1 for p in peers if p.reachable)
    out.append(f'sdfr_peers{{state="reachable"}} {reachable}')
    out.append(f'sdfr_peers{{state="known"}} {len(peers)}')
    family("sdfr_local_services", "gauge", "Services this robot publishes.")
    out.append(f"sdfr_local_services {len(local)}")
    family("sdfr_discovery_up", "gauge", "1 when the discovery layer is alive and heartbeating.")
    out.append(f"sdfr_discovery_up {int(disc.up)}")
    family(
        "sdfr_discovery_errors",
        "gauge",
        "Failures of the discovery layer's callbacks in the last minute.",
    )
    out.append(f"sdfr_discovery_errors {status.errors.recent}")
    family("sdfr_auth_mode", "gauge", "The keyring's mode (open: no key).")
    for name in ("open", "accept", "sign", "enforce"):
        out.append(f'sdfr_auth_mode{{mode="{name}"}} {int(status.auth.mode == name)}')
    family("sdfr_auth_verified_total", "counter", "Datagrams whose seal checked out, by key id.")
    for kid, count in sorted(status.auth.received.items()):
        out.append(f'sdfr_auth_verified_total{{key="{_label(kid)}"}} {count}')
    family(
        "sdfr_challenges_total",
        "counter",
        "Pings sent to check a claim before believing it (a new robot, an older boot, ...).",
    )
    out.append(f"sdfr_challenges_total {c.challenges}")
    family(
        "sdfr_challenges_limited_total",
        "counter",
        "Challenges not sent because too many were due at once (a flood of claims).",
    )
    out.append(f"sdfr_challenges_limited_total {c.challenges_limited}")
    family(
        "sdfr_robot_id_conflicts_total",
        "counter",
        "Datagrams from another sender claiming this robot's id.",
    )
    conflict = status.robot_id_conflict
    out.append(f"sdfr_robot_id_conflicts_total {0 if conflict is None else conflict.count}")
    family(
        "sdfr_api_request_seconds",
        "histogram",
        "Time the REST API took to answer, by method and route template.",
    )
    for (method, route), hist in sorted(state.latency.items()):
        labels = f'method="{method}",route="{_label(route)}"'
        cumulative = 0
        for bound, n in zip(LATENCY_BUCKETS, hist.buckets, strict=True):
            cumulative += n
            out.append(f'sdfr_api_request_seconds_bucket{{{labels},le="{bound}"}} {cumulative}')
        out.append(f'sdfr_api_request_seconds_bucket{{{labels},le="+Inf"}} {hist.count}')
        out.append(f"sdfr_api_request_seconds_sum{{{labels}}} {hist.total!r}")
        out.append(f"sdfr_api_request_seconds_count{{{labels}}} {hist.count}")
    return "\n".join(out) + "\n"


async def metrics(request: web.Request) -> web.Response:
    body = metrics_text(_state(request)).encode()
    return web.Response(body=body, headers={"Content-Type": "text/plain; version=0.0.4"})


# -- the OpenAPI document ----------------------------------------------------------------------


def _ref(name: str) -> dict[str, str]:
    return {"$ref": f"#/components/schemas/{name}"}


def _json_content(schema: dict[str, Any]) -> dict[str, Any]:
    return {"application/json": {"schema": schema}}


def _answer(text: str, schema: str) -> dict[str, Any]:
    return {"description": text, "content": _json_content(_ref(schema))}


_ERROR = _answer("An error; `field` names the offending field or parameter.", "Error")
_ERRORS_400 = {"400": _ERROR, "422": _ERROR}
_DOORS = {
    **_ERROR,
    "description": "A web page's cross-site request (Origin, Sec-Fetch-Site) or a Host that "
    "is not one of this API's names (see api_allowed_origins, api_allowed_hosts)",
}


def openapi_document() -> dict[str, Any]:
    """The OpenAPI 3.1 description of `create_app`'s routes."""
    attr_value = {"type": ["string", "number", "integer", "boolean"]}
    service_fields = {
        "name": {"type": "string", "minLength": 1, "maxLength": 128},
        "type": {
            "type": "string",
            "pattern": "^[A-Za-z0-9][A-Za-z0-9._:/-]{0,127}$",
            "description": "What the service is, e.g. `camera/rgb`; searched by equality.",
        },
        "url": {"type": ["string", "null"], "maxLength": 256},
        "attributes": {
            "type": "object",
            "maxProperties": 32,
            "additionalProperties": attr_value,
            "description": "Capabilities, searched with `attr.KEY=VALUE` (booleans as "
            "`true`/`false`, numbers in their JSON text).",
        },
    }
    nullable_number = {"type": ["number", "null"]}
    neighbor_properties: dict[str, Any] = {
        "robot_id": {"type": "string"},
        "address": {"type": "string", "description": "IPv4 address on the fleet network"},
        "reachable": {"type": "boolean"},
        "indicator": {
            **nullable_number,
            "description": "Connection indicator: success rate 0-1 of recent unicast pings",
        },
        "rtt_ms": {**nullable_number, "description": "Mean round-trip time of recent pings"},
        "last_seen": {"type": "number", "description": "Unix time the robot was last heard"},
        "services": {"type": "array", "items": _ref("Service")},
    }
    neighbor = {
        "type": "object",
        "required": ["robot_id", "address", "reachable", "indicator", "rtt_ms", "services"],
        "properties": neighbor_properties,
    }
    peer_record = {
        "type": "object",
        "required": ["robot_id", "address", "reachable", "boot_id", "version", "services"],
        "properties": {
            **neighbor_properties,
            "location": {"type": "string", "description": "URL of its description"},
            "boot_id": {"type": "integer"},
            "version": {"type": "integer", "description": "Version of its service set"},
            "first_seen": {"type": "number"},
        },
    }
    schemas: dict[str, Any] = {
        "Error": {
            "type": "object",
            "required": ["error", "field"],
            "properties": {
                "error": {"type": "string"},
                "field": {"type": ["string", "null"]},
            },
        },
        "ServiceInput": {
            "type": "object",
            "required": ["name", "type"],
            "additionalProperties": False,
            "properties": {
                "id": {
                    "type": "string",
                    "pattern": "^[A-Za-z0-9._-]{1,64}$",
                    "description": "Chosen by the client to make the publish idempotent: the "
                    "same service again is a 200, another one under this id a 409. Left out, "
                    "the robot picks one.",
                },
                **service_fields,
            },
            "description": "A registration; one service must fit in one datagram.",
        },
        "Service": {
            "type": "object",
            "required": ["id", "name", "type", "url", "attributes"],
            "properties": {"id": {"type": "string"}, **service_fields},
        },
        "Published": {
            "type": "object",
            "required": ["id", "service", "version"],
            "properties": {
                "id": {"type": "string"},
                "service": _ref("Service"),
                "version": {"type": "integer"},
            },
        },
        "Services": {
            "type": "object",
            "required": ["services", "version"],
            "properties": {
                "services": {"type": "array", "items": _ref("Service")},
                "version": {
                    "type": "integer",
                    "description": "Bumped by every publish and unpublish",
                },
            },
        },
        "Neighbor": neighbor,
        "Neighbors": {
            "type": "object",
            "required": ["neighbors"],
            "properties": {"neighbors": {"type": "array", "items": _ref("Neighbor")}},
        },
        "PeerRecord": peer_record,
        "History": {
            "type": "object",
            "required": ["robots"],
            "properties": {"robots": {"type": "array", "items": _ref("PeerRecord")}},
        },
        "Self": {
            "type": "object",
            "required": ["robot_id", "fleet", "address", "version", "services", "discovery"],
            "properties": {
                "robot_id": {"type": ["string", "null"]},
                "fleet": {"type": "integer"},
                "iface": {"type": ["string", "null"]},
                "address": {"type": "string"},
                "boot_id": {"type": ["integer", "null"]},
                "version": {"type": "integer"},
                "location": {"type": ["string", "null"]},
                "software": {"type": "string"},
                "services": {"type": "array", "items": _ref("Service")},
                "discovery": {
                    "type": "object",
                    "required": ["up"],
                    "properties": {
                        "up": {"type": "boolean"},
                        "heartbeat_age": nullable_number,
                        "pid": {"type": ["integer", "null"]},
                        "iface": {"type": ["string", "null"]},
                        "started": nullable_number,
                        "announced_version": {"type": ["integer", "null"]},
                        "peers_reachable": {"type": ["integer", "null"]},
                        "peers_known": {"type": ["integer", "null"]},
                    },
                },
            },
        },
        "Health": {
            "type": "object",
            "required": [
                "status",
                "api",
                "discovery",
                "discovery_heartbeat_age",
                "discovery_error",
                "state",
                "state_error",
                "auth",
                "warnings",
            ],
            "properties": {
                "status": {
                    "enum": ["ok", "warning", "degraded"],
                    "description": "degraded: the discovery layer is down or failing, or the "
                    "state directory cannot be written (503); warning: up, with warnings",
                },
                "api": {"const": "up"},
                "discovery": {
                    "enum": ["up", "failing", "down"],
                    "description": "failing: alive, but its work keeps failing or it cannot "
                    "announce this robot's services (see discovery_error)",
                },
                "discovery_heartbeat_age": nullable_number,
                "discovery_error": {"type": ["string", "null"]},
                "state": {
                    "enum": ["ok", "full", "read-only", "error"],
                    "description": "Whether the state directory can be written (publishes "
                    "need it); not ok answers 503 with the discovery layer up",
                },
                "state_error": {"type": ["string", "null"]},
                "auth": {
                    "enum": ["open", "accept", "sign", "enforce", None],
                    "description": "The keyring's mode; open: no fleet key",
                },
                "warnings": {
                    "type": "array",
                    "items": {"type": "string"},
                    "description": "e.g. another daemon claims this robot's id",
                },
            },
        },
        "Keys": {
            "type": "object",
            "required": ["mode", "primary", "keyed", "ssdp_interop", "keys"],
            "properties": {
                "mode": {"enum": ["open", "accept", "sign", "enforce"]},
                "primary": {"type": ["string", "null"], "description": "The key that signs"},
                "keyed": {"type": "boolean"},
                "ssdp_interop": {"type": "boolean"},
                "keys": {
                    "type": "array",
                    "items": {
                        "type": "object",
                        "required": ["id", "primary", "installed", "received"],
                        "properties": {
                            "id": {"type": "string", "description": "8 hex characters"},
                            "primary": {"type": "boolean"},
                            "installed": nullable_number,
                            "received": {
                                "type": "integer",
                                "description": "Datagrams verified with it since the "
                                "discovery layer started",
                            },
                        },
                    },
                },
            },
        },
    }
    key_id_param = [{"name": "id", "in": "path", "required": True, "schema": {"type": "string"}}]
    unix_only = (
        "Only on the unix socket STATE_DIR/api.sock (403 over TCP). Never returns key material."
    )
    paths: dict[str, Any] = {
        "/services": {
            "get": {
                "summary": "This robot's registrations",
                "responses": {"200": _answer("The local services", "Services")},
            },
            "post": {
                "summary": "Publish a service",
                "requestBody": {"required": True, "content": _json_content(_ref("ServiceInput"))},
                "responses": {
                    "201": {
                        **_answer("Published, on disk", "Published"),
                        "headers": {
                            "Location": {"schema": {"type": "string"}, "description": "Its URL"}
                        },
                    },
                    "200": _answer("Published already under this id (a retry)", "Published"),
                    **_ERRORS_400,
                    "409": {**_ERROR, "description": "The id is another service's"},
                    "413": _ERROR,
                    "503": {**_ERROR, "description": "The state directory is read-only"},
                    "507": {
                        **_ERROR,
                        "description": "The state directory is full, or the robot's services "
                        "would need more than the 255 Update parts one announcement can carry",
                    },
                },
            },
        },
        "/services/{id}": {
            "delete": {
                "summary": "Unpublish a service",
                "parameters": [
                    {"name": "id", "in": "path", "required": True, "schema": {"type": "string"}}
                ],
                "responses": {"204": {"description": "Unpublished"}, "404": _ERROR},
            }
        },
        "/neighbors": {
            "get": {
                "summary": "Robots reachable now, with their services",
                "parameters": [
                    {
                        "name": "all",
                        "in": "query",
                        "required": False,
                        "schema": {"enum": ["1", "0", "true", "false", "yes", "no"]},
                        "description": "Also the unreachable robots of the history map",
                    }
                ],
                "responses": {"200": _answer("The neighbours", "Neighbors"), "422": _ERROR},
            }
        },
        "/neighbors/search": {
            "get": {
                "summary": "Reachable robots offering matching services (only those services)",
                "description": "At least one criterion. Any number of `attr.KEY=VALUE` "
                "parameters, one per attribute; a service matches when its type and every "
                "given attribute are equal.",
                "parameters": [
                    {
                        "name": "type",
                        "in": "query",
                        "required": False,
                        "schema": {"type": "string"},
                    },
                    {
                        "name": "attr.KEY",
                        "in": "query",
                        "required": False,
                        "schema": {"type": "string"},
                        "description": "Replace KEY by the attribute's name",
                    },
                ],
                "responses": {"200": _answer("The matches", "Neighbors"), "422": _ERROR},
            }
        },
        "/history": {
            "get": {
                "summary": "Every robot ever seen, reachable or not",
                "responses": {"200": _answer("The history map", "History")},
            }
        },
        "/self": {
            "get": {
                "summary": "This robot: identity, address, services, discovery state",
                "responses": {"200": _answer("This robot", "Self")},
            }
        },
        "/health": {
            "get": {
                "summary": "Liveness of the two layers",
                "responses": {
                    "200": _answer("Both layers up", "Health"),
                    "503": _answer("The discovery layer is down; the API answers", "Health"),
                },
            }
        },
        "/openapi.json": {
            "get": {
                "summary": "This document",
                "responses": {"200": {"description": "OpenAPI 3.1", "content": _json_content({})}},
            }
        },
        "/keys": {
            "get": {
                "summary": "The fleet keyring: key ids, the one that signs, the mode",
                "description": unix_only,
                "responses": {"200": _answer("The keyring", "Keys"), "403": _ERROR},
            },
            "post": {
                "summary": "Install a key (accepted at once, used to sign after `use`)",
                "description": unix_only + " The first key of a robot without any is put to "
                "use in mode accept.",
                "requestBody": {
                    "required": True,
                    "content": _json_content(
                        {
                            "type": "object",
                            "required": ["key"],
                            "additionalProperties": False,
                            "properties": {
                                "key": {"type": "string", "description": "base64, 32 bytes"}
                            },
                        }
                    ),
                },
                "responses": {
                    "201": _answer("Installed", "Keys"),
                    "200": _answer("Installed already", "Keys"),
                    "403": _ERROR,
                    **_ERRORS_400,
                },
            },
        },
        "/keys/{id}/use": {
            "post": {
                "summary": "Sign with this key from now on",
                "description": unix_only,
                "parameters": key_id_param,
                "responses": {"200": _answer("The keyring", "Keys"), "403": _ERROR, "404": _ERROR},
            }
        },
        "/keys/{id}": {
            "delete": {
                "summary": "Stop accepting this key (never the one in use)",
                "description": unix_only,
                "parameters": key_id_param,
                "responses": {
                    "204": {"description": "Removed"},
                    "403": _ERROR,
                    "404": _ERROR,
                    "409": _ERROR,
                },
            }
        },
        "/keys/mode": {
            "put": {
                "summary": "accept, sign or enforce (the steps of moving a fleet to a key)",
                "description": unix_only,
                "requestBody": {
                    "required": True,
                    "content": _json_content(
                        {
                            "type": "object",
                            "required": ["mode"],
                            "additionalProperties": False,
                            "properties": {"mode": {"enum": ["accept", "sign", "enforce"]}},
                        }
                    ),
                },
                "responses": {
                    "200": _answer("The keyring", "Keys"),
                    "403": _ERROR,
                    "409": _ERROR,
                    **_ERRORS_400,
                },
            }
        },
        "/metrics": {
            "get": {
                "summary": "Prometheus metrics",
                "responses": {
                    "200": {
                        "description": "Text exposition format 0.0.4",
                        "content": {"text/plain": {"schema": {"type": "string"}}},
                    }
                },
            }
        },
    }
    keyring_errors = {
        "500": {
            **_ERROR,
            "description": "STATE_DIR/keyring.json cannot be read or written (damaged, "
            "unreadable); `field` is keyring and the error names the file",
        },
        "503": {**_ERROR, "description": "The state directory is read-only"},
        "507": {**_ERROR, "description": "The state directory is full"},
    }
    for path, ops in paths.items():
        for method, op in ops.items():
            if path.startswith("/keys"):  # a GET only reads the keyring
                errors = keyring_errors if method != "get" else {"500": keyring_errors["500"]}
                op["responses"].update(errors)
            op["responses"].setdefault("403", _DOORS)
            op["responses"].setdefault("405", _ERROR)
            op["responses"].setdefault("500", _ERROR)
            if "requestBody" in op:
                op["responses"].setdefault("408", _ERROR)
                op["responses"].setdefault("415", {**_ERROR, "description": "Not a JSON body"})
    return {
        "openapi": "3.1.0",
        "info": {
            "title": "SDfR local API",
            "version": __version__,
            "description": "Publish this robot's services; ask which robots are reachable and "
            "what they offer. Every answer, errors included, is JSON (except /metrics).",
        },
        "paths": paths,
        "components": {"schemas": schemas},
    }


# -- applications ------------------------------------------------------------------------------


_PARSE_ERRORS = {
    400: "malformed HTTP request",
    413: "the request is too large",
    414: "the request line (path and query) is longer than 8190 bytes",
    431: "a request header is longer than 8190 bytes, or there are too many",
}


class _JsonErrorHandler(RequestHandler):
    """aiohttp's connection handler, answering what fails before any handler runs (a
    malformed request, an oversize line or header, a method no parser knows) in JSON like
    every other error, and logging it at debug level (a port scan must not fill the log)."""

    def handle_error(
        self,
        request: BaseRequest,
        status: int = 500,
        exc: BaseException | None = None,
        message: str | None = None,
    ) -> web.StreamResponse:
        log.debug("%s from %s: %s", status, request.remote, message or exc)
        if request.writer.output_size > 0:
            raise ConnectionError("a response was sent already; cannot send an error")
        text = _PARSE_ERRORS.get(status, "internal error; the daemon's log has the details")
        detail = (message or "").strip().splitlines()
        if isinstance(exc, LineTooLong):
            text = "the request line or a header is longer than 8190 bytes"
        elif status == 400 and detail:
            text = f"{text}: {detail[0][:120]}"
        resp = _error(status, text)
        resp.force_close()
        return resp


class _JsonErrorServer(web.Server):
    def __call__(self) -> RequestHandler:
        return _JsonErrorHandler(self, loop=self._loop, **self._kwargs)


class Runner(web.AppRunner):
    """An AppRunner whose every answer is JSON (see _JsonErrorHandler) and which closes idle
    and half-sent connections after IDLE_TIMEOUT."""

    def __init__(self, app: web.Application, **kwargs: Any) -> None:
        kwargs.setdefault("keepalive_timeout", IDLE_TIMEOUT)
        super().__init__(app, **kwargs)

    async def _make_server(self) -> web.Server:
        server = await super()._make_server()
        server.__class__ = _JsonErrorServer  # same state; only __call__ differs
        return server


def create_app(cfg: Config, store: Store) -> web.Application:
    """The local REST API."""
    app = web.Application(middlewares=[_measure, _errors_as_json, _doors], client_max_size=MAX_BODY)
    writer = Writer(cfg.state_dir)
    app[STATE] = ApiState(
        cfg=cfg, view=StoreView(store, cfg), writer=writer, hosts=allowed_hosts(cfg)
    )

    async def close_writer(app: web.Application) -> None:
        writer.close()

    app.on_cleanup.append(close_writer)
    openapi_body = _json_bytes(openapi_document())

    async def openapi(request: web.Request) -> web.Response:
        return _json_response(openapi_body)

    routes: list[tuple[str, str, Handler]] = [
        ("GET", "/services", list_services),
        ("POST", "/services", publish),
        ("DELETE", "/services/{id}", unpublish),
        ("GET", "/neighbors", neighbors),
        ("GET", "/neighbors/search", search),
        ("GET", "/history", history),
        ("GET", "/self", self_info),
        ("GET", "/health", health),
        ("GET", "/openapi.json", openapi),
        ("GET", "/metrics", metrics),
        ("GET", "/keys", keys_list),
        ("POST", "/keys", keys_install),
        ("POST", "/keys/{id}/use", keys_use),
        ("DELETE", "/keys/{id}", keys_remove),
        ("PUT", "/keys/mode", keys_mode),
    ]
    for method, path, handler in routes:
        app.router.add_route(method, path, handler)
    return app
