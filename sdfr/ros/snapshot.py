"""What the bridge reads from sdfrd: the neighbour list as a `Snapshot` of `Robot`s, decoded
from the API's records (`sdfr.records.schema`); the bridge (`core`) and the change sources
(`source`) both take it from here."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import msgspec

from sdfr.client import Client
from sdfr.errors import SdfrError
from sdfr.records.model import Service, ServiceOutput
from sdfr.records.schema import LocalService, Neighbor


class BridgeError(SdfrError):
    """A request of a ROS client could not be carried out; the message says why."""


@dataclass(frozen=True, slots=True)
class Robot:
    """A robot as sdfrd lists it."""

    robot_id: str
    address: str
    reachable: bool
    indicator: float | None
    rtt_ms: float | None
    last_seen: float
    services: tuple[Service, ...] = ()

    def service_map(self) -> dict[str, Service]:
        return {s.id: s for s in self.services}


@dataclass(frozen=True, slots=True)
class Snapshot:
    """The neighbour list as read at `stamp` (seconds since the epoch)."""

    stamp: float
    robots: tuple[Robot, ...]

    def by_id(self) -> dict[str, Robot]:
        return {r.robot_id: r for r in self.robots}


def _service(s: ServiceOutput) -> Service:
    return Service(id=s.id, name=s.name, type=s.type, url=s.url, attributes=s.attributes)


#: The keys of a service the bridge reads; others (a field a newer sdfrd adds) are left out
#: before the record is checked, since the schema's service refuses unknown keys.
_SERVICE_KEYS = frozenset(LocalService.__struct_fields__)


def _known(service: object) -> object:
    if isinstance(service, dict):
        return {k: v for k, v in service.items() if k in _SERVICE_KEYS}
    return service


def _known_services(items: object) -> object:
    """`items` (a robot list) with each service's unknown keys left out."""
    if not isinstance(items, list):
        return items
    return [
        {**r, "services": [_known(s) for s in r["services"]]}
        if isinstance(r, dict) and isinstance(r.get("services"), list)
        else r
        for r in items
    ]


def robots_from_json(items: object, what: str = "neighbors") -> tuple[Robot, ...]:
    """The daemon's robot list (`sdfr.records.schema.Neighbor`s), checked; BridgeError naming what
    was wrong otherwise."""
    try:
        parsed = msgspec.convert(_known_services(items), list[Neighbor])
    except msgspec.ValidationError as exc:
        raise BridgeError(f"unexpected answer from sdfrd for {what}: {exc}") from None
    return tuple(
        Robot(
            robot_id=r.robot_id,
            address=r.address,
            reachable=r.reachable,
            indicator=r.indicator,
            rtt_ms=r.rtt_ms,
            last_seen=r.last_seen,
            services=tuple(_service(s) for s in r.services),
        )
        for r in parsed
    )


def services_from_json(items: object) -> tuple[Service, ...]:
    """This robot's registrations (`sdfr.records.schema.LocalService`s) as services (a lease's `ttl`
    and `expires` left out)."""
    try:
        parsed = msgspec.convert(
            [_known(s) for s in items] if isinstance(items, list) else items, list[LocalService]
        )
    except msgspec.ValidationError as exc:
        raise BridgeError(f"unexpected answer from sdfrd for services: {exc}") from None
    return tuple(_service(s) for s in parsed)


def read_snapshot(client: Client, clock: Callable[[], float] = time.time) -> Snapshot:
    """The reachable robots now; ApiError when sdfrd cannot be read."""
    return Snapshot(stamp=clock(), robots=robots_from_json(client.neighbors()))
