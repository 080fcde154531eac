"""The bridge between sdfrd and ROS, without ROS.

It talks to the local sdfrd only through its REST API.  The adapters (`sdfr.ros.ros2`,
`sdfr.ros.ros1`) hand it what arrives on the node's topics and services and give it a
`Sink` that publishes what it produces: the neighbour list, change events, diagnoses.
"""

from __future__ import annotations

import enum
import hashlib
import logging
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

from sdfr.client import Client, user_owner_token
from sdfr.errors import ApiError
from sdfr.records.model import (
    AttrValue,
    Service,
)
from sdfr.ros.params import NodeParams
from sdfr.ros.snapshot import (
    BridgeError,
    Robot,
    Snapshot,
    robots_from_json,
    services_from_json,
)
from sdfr.ros.source import ChangeSource, EventStreamSource, PollingSource
from sdfr.ros.spawn import SpawnedDaemon, ensure_daemon, stop_daemon

__all__ = [
    "QUALITY_REFRESH",
    "Bridge",
    "BridgeError",
    "Change",
    "ChangeKind",
    "Diagnosis",
    "Level",
    "Listing",
    "Robot",
    "ServiceRequest",
    "Sink",
    "Snapshot",
    "diagnosis_of",
    "diff",
    "robots_from_json",
    "services_from_json",
]

log = logging.getLogger("sdfr.ros")

#: ~/neighbors is republished at once on a change of membership, address or services; when
#: only the connection indicator or RTT moved, at most this often (seconds).
QUALITY_REFRESH = 5.0


# -- what the bridge hands out -------------------------------------------------------------------


class ChangeKind(enum.IntEnum):
    """The values of sdfr_msgs/Change's constants."""

    ROBOT_ADDED = 1
    ROBOT_REMOVED = 2
    ROBOT_UPDATED = 3
    SERVICE_ADDED = 4
    SERVICE_REMOVED = 5
    SERVICE_UPDATED = 6


@dataclass(frozen=True, slots=True)
class Change:
    stamp: float
    kind: ChangeKind
    robot_id: str
    address: str
    service: Service | None = None


class Level(enum.IntEnum):
    """diagnostic_msgs/DiagnosticStatus's levels."""

    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3


@dataclass(frozen=True, slots=True)
class Diagnosis:
    """The daemon's health as one diagnostic status."""

    level: Level
    message: str
    robot_id: str = ""
    values: tuple[tuple[str, str], ...] = ()


@dataclass(frozen=True, slots=True)
class Listing:
    """The answer of ~/list."""

    robot_id: str
    services: tuple[Service, ...]
    robots: tuple[Robot, ...]


class Sink(Protocol):
    """What an adapter publishes.  Called from the bridge's own threads."""

    def neighbors(self, snapshot: Snapshot, robot_id: str) -> None: ...

    def changes(self, changes: Sequence[Change]) -> None: ...

    def diagnostics(self, diagnosis: Diagnosis) -> None: ...


# -- changes ---------------------------------------------------------------------------------


def diff(old: Snapshot | None, new: Snapshot) -> list[Change]:
    """The changes from `old` to `new`, robots in order of id; a robot that arrives gives
    ROBOT_ADDED then SERVICE_ADDED per service, one that leaves SERVICE_REMOVED per service
    then ROBOT_REMOVED.  Indicator, RTT and last_seen are no change."""
    before = old.by_id() if old is not None else {}
    after = new.by_id()
    t = new.stamp
    out: list[Change] = []
    for rid in sorted(before.keys() | after.keys()):
        was, now = before.get(rid), after.get(rid)
        if was is None and now is not None:
            out.append(Change(t, ChangeKind.ROBOT_ADDED, rid, now.address))
            out += [Change(t, ChangeKind.SERVICE_ADDED, rid, now.address, s) for s in _ordered(now)]
        elif now is None and was is not None:
            out += [
                Change(t, ChangeKind.SERVICE_REMOVED, rid, was.address, s) for s in _ordered(was)
            ]
            out.append(Change(t, ChangeKind.ROBOT_REMOVED, rid, was.address))
        elif was is not None and now is not None:
            if was.address != now.address:
                out.append(Change(t, ChangeKind.ROBOT_UPDATED, rid, now.address))
            out += _service_changes(t, was, now)
    return out


def _ordered(robot: Robot) -> list[Service]:
    return sorted(robot.services, key=lambda s: s.id)


def _service_changes(t: float, was: Robot, now: Robot) -> list[Change]:
    old, new = was.service_map(), now.service_map()
    out: list[Change] = []
    for sid in sorted(old.keys() | new.keys()):
        a, b = old.get(sid), new.get(sid)
        if a is None and b is not None:
            out.append(Change(t, ChangeKind.SERVICE_ADDED, now.robot_id, now.address, b))
        elif b is None and a is not None:
            out.append(Change(t, ChangeKind.SERVICE_REMOVED, now.robot_id, now.address, a))
        elif a is not None and b is not None and _differs(a, b):
            out.append(Change(t, ChangeKind.SERVICE_UPDATED, now.robot_id, now.address, b))
    return out


def _differs(a: Service, b: Service) -> bool:
    return a.to_json() != b.to_json()


def _quality(snapshot: Snapshot) -> dict[str, tuple[float | None, float | None]]:
    return {r.robot_id: (r.indicator, r.rtt_ms) for r in snapshot.robots}


# -- publishing ------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ServiceRequest:
    """What arrives on ~/publish or ~/unpublish."""

    name: str
    type: str
    id: str = ""
    url: str = ""
    attributes: Mapping[str, AttrValue] = field(default_factory=dict)

    def service_id(self) -> str:
        """`id`, or one derived from type and name: the same message unpublishes what it
        published, and publishing it again stores nothing twice."""
        if self.id:
            return self.id
        digest = hashlib.sha256(f"{self.type}\n{self.name}".encode()).hexdigest()
        return "ros-" + digest[:12]


def _level(health: Mapping[str, Any]) -> Level:
    status = health.get("status")
    if status == "ok":
        return Level.OK
    if status == "warning":
        return Level.WARN
    return Level.ERROR


def diagnosis_of(
    health: Mapping[str, Any], robot_id: str, spawned: SpawnedDaemon | None
) -> Diagnosis:
    """GET /health as one diagnostic status."""
    level = _level(health)
    if level is Level.OK:
        message = "sdfrd is up"
    elif level is Level.WARN:
        message = "; ".join(str(w) for w in health.get("warnings") or []) or "sdfrd warns"
    else:
        why = health.get("discovery_error") or health.get("state_error")
        message = (
            f"sdfrd is degraded: discovery {health.get('discovery')}, state {health.get('state')}"
        )
        message += f" ({why})" if why else ""
    keys = ("status", "discovery", "discovery_heartbeat_age", "state", "auth")
    values = [(k, _text(health.get(k))) for k in keys]
    values.append(("warnings", "; ".join(str(w) for w in health.get("warnings") or [])))
    values.append(("started_by_node", "yes" if spawned is not None else "no"))
    if spawned is not None:
        values.append(("sdfrd_pid", str(spawned.proc.pid)))
    return Diagnosis(level, message, robot_id, tuple(values))


def _text(value: object) -> str:
    return "" if value is None else str(value)


# -- the bridge ------------------------------------------------------------------------------


class Bridge:
    """sdfrd seen through its API: requests from ROS in, neighbours/changes/health out.

    `start()` makes sure a daemon answers (starting one if allowed), then runs the change
    source and the health reports on threads of their own; `close()` stops them, and the
    daemon if it started it.  Requests (`publish`, `search`, ...) may come from any thread.
    """

    def __init__(
        self,
        params: NodeParams,
        sink: Sink,
        *,
        source: ChangeSource | None = None,
        connect: Callable[[], Client] | None = None,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.params = params
        self.sink = sink
        self.clock = clock
        # The user's owner token (as `sdfr` keeps it): what the node published, a respawned
        # node may publish again or unpublish (its ids are derived from the messages).
        token = user_owner_token() if connect is None else None
        self._connect = connect or (
            lambda: Client(params.api, timeout=5.0, retry_delays=(), owner_token=token)
        )
        polling = PollingSource(self._connect, params.poll_interval, clock)
        self.source = source or EventStreamSource(
            self._connect, polling, refresh=QUALITY_REFRESH, clock=clock
        )
        self.spawned: SpawnedDaemon | None = None
        self._client = self._connect()
        self._lock = threading.Lock()  # one request at a time on self._client
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._last: Snapshot | None = None
        self._last_quality: dict[str, tuple[float | None, float | None]] = {}
        self._published_at = 0.0
        self._robot_id = ""
        self._snapshot_lock = threading.Lock()

    # -- life cycle ----------------------------------------------------------------------------

    def start(self) -> None:
        self.spawned = ensure_daemon(self.params, self._connect)
        self._refresh_robot_id()
        for name, target in (("source", self._run_source), ("health", self._run_health)):
            thread = threading.Thread(target=target, name=f"sdfr-bridge-{name}", daemon=True)
            thread.start()
            self._threads.append(thread)

    def close(self) -> None:
        """Stop the threads; stop sdfrd only if this bridge started it."""
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=10)
        self._threads.clear()
        with self._lock:
            self._client.close()
        if self.spawned is not None:
            stop_daemon(self.spawned)
            self.spawned = None

    def __enter__(self) -> Bridge:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def robot_id(self) -> str:
        return self._robot_id

    def _refresh_robot_id(self) -> None:
        try:
            info = self._call(lambda c: c.self_info())
        except BridgeError:
            return
        rid = info.get("robot_id") if isinstance(info, dict) else None
        if isinstance(rid, str):
            self._robot_id = rid

    # -- what the threads do -------------------------------------------------------------------

    def _run_source(self) -> None:
        try:
            self.source.run(self.on_snapshot, self._stop)
        except Exception:  # a bug in a source must not pass silently
            log.exception("the change source stopped")
            self.sink.diagnostics(
                Diagnosis(Level.ERROR, "the bridge's change source stopped (see the log)")
            )

    def _run_health(self) -> None:
        while not self._stop.is_set():
            try:
                self.sink.diagnostics(self.check_health())
            except Exception:
                log.exception("health report failed")
            self._stop.wait(self.params.diagnostics_period)

    def on_snapshot(self, snapshot: Snapshot) -> None:
        """A neighbour list from the source: changes, and ~/neighbors when it changed."""
        with self._snapshot_lock:
            changes = diff(self._last, snapshot)
            quality = _quality(snapshot)
            first = self._last is None
            stale = quality != self._last_quality and (
                snapshot.stamp - self._published_at >= QUALITY_REFRESH
            )
            self._last = snapshot
            if not (changes or first or stale):
                return
            self._last_quality = quality
            self._published_at = snapshot.stamp
            if changes:
                self.sink.changes(changes)
            self.sink.neighbors(snapshot, self._robot_id)

    def check_health(self) -> Diagnosis:
        spawned = self.spawned
        if spawned is not None and spawned.proc.poll() is not None:
            return Diagnosis(
                Level.ERROR,
                f"the sdfrd this node started exited with status {spawned.proc.returncode} "
                f"(its output: {spawned.log_path})",
                self._robot_id,
            )
        try:
            health = self._call(lambda c: c.health())
        except BridgeError as exc:
            return Diagnosis(Level.ERROR, str(exc), self._robot_id, (("api", self.params.api),))
        if not self._robot_id:
            self._refresh_robot_id()
        diagnosis = diagnosis_of(health, self._robot_id, spawned)
        return Diagnosis(
            diagnosis.level,
            diagnosis.message,
            diagnosis.robot_id,
            (("api", self.params.api), *diagnosis.values),
        )

    # -- requests from ROS ---------------------------------------------------------------------

    def _call(self, fn: Callable[[Client], Any]) -> Any:
        with self._lock:
            try:
                return fn(self._client)
            except ApiError as exc:
                if exc.status == 0:
                    raise BridgeError(f"{exc}; is sdfrd running?") from None
                raise BridgeError(str(exc)) from None

    def publish(self, request: ServiceRequest) -> str:
        """Publish (or replace) a service of this robot; its id."""
        sid = request.service_id()
        args = (request.name, request.type, request.url or None, dict(request.attributes))
        with self._lock:
            try:
                try:
                    self._client.publish_service(*args, service_id=sid)
                except ApiError as exc:
                    if exc.status != 409:
                        raise
                    # Another service under this id: the newest message wins.
                    self._client.unpublish(sid)
                    self._client.publish_service(*args, service_id=sid)
            except ApiError as exc:
                raise BridgeError(f"cannot publish {request.name!r}: {_reason(exc)}") from None
        return sid

    def unpublish(self, request: ServiceRequest) -> str:
        """Withdraw the service `request` names (by its id, or the one derived from it)."""
        sid = request.service_id()
        with self._lock:
            try:
                self._client.unpublish(sid)
            except ApiError as exc:
                if exc.status == 404:
                    raise BridgeError(
                        f"cannot unpublish {sid!r}: this robot has no such service"
                    ) from None
                raise BridgeError(f"cannot unpublish {sid!r}: {_reason(exc)}") from None
        return sid

    def search(self, type: str, attributes: Mapping[str, AttrValue]) -> tuple[Robot, ...]:
        """Reachable robots with a matching service, each with only those services."""
        if not type and not attributes:
            raise BridgeError("search: give a type or at least one attribute")
        found = self._call(lambda c: c.search(type or None, dict(attributes)))
        return robots_from_json(found, "search")

    def listing(self, include_unreachable: bool = False) -> Listing:
        """This robot's services and the robots it knows (reachable, or all of history)."""
        own = services_from_json(self._call(lambda c: c.services()))
        robots = robots_from_json(self._call(lambda c: c.neighbors(include_unreachable)))
        if not self._robot_id:
            self._refresh_robot_id()
        return Listing(self._robot_id, own, robots)


def _reason(exc: ApiError) -> str:
    if exc.status == 0:
        return f"{exc}; is sdfrd running?"
    return str(exc)
