"""The bridge's values as sdfr_msgs messages and back, for ROS 1 and ROS 2 alike.

The generated classes of both versions take the same keyword arguments; what differs (the
time type, the type of diagnostic_msgs' `level`) comes in an `Interfaces`.  Nothing here
imports ROS: the adapters pass their classes in.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from sdfr.records.model import AttrValue, Service
from sdfr.ros.core import BridgeError, Change, Diagnosis, ServiceRequest
from sdfr.ros.snapshot import Robot, Snapshot

# sdfr_msgs/Attribute's type constants
STRING, INTEGER, DOUBLE, BOOL = 0, 1, 2, 3
_TYPE_NAMES = "STRING(0), INTEGER(1), DOUBLE(2), BOOL(3)"
#: Name of the diagnostic status the node publishes.
DIAGNOSTIC_NAME = "sdfr: sdfrd"


@dataclass(frozen=True, slots=True)
class Interfaces:
    """The message classes of one ROS version."""

    Attribute: Any
    Service: Any
    Robot: Any
    NeighborList: Any
    Change: Any
    DiagnosticArray: Any
    DiagnosticStatus: Any
    KeyValue: Any
    Header: Any
    time: Callable[[float], Any]  # seconds since the epoch -> the version's time
    level: Callable[[int], Any]  # DiagnosticStatus.level: bytes in ROS 2, int in ROS 1

    @classmethod
    def of(
        cls,
        msg: Any,
        diagnostic: Any,
        std: Any,
        *,
        stamp: Callable[[int, int], Any],
        level: Callable[[int], Any],
    ) -> Interfaces:
        """The classes of the modules sdfr_msgs.msg, diagnostic_msgs.msg and std_msgs.msg,
        which have the same names in both versions; `stamp` makes the version's time of
        (seconds, nanoseconds)."""
        return cls(
            Attribute=msg.Attribute,
            Service=msg.Service,
            Robot=msg.Robot,
            NeighborList=msg.NeighborList,
            Change=msg.Change,
            DiagnosticArray=diagnostic.DiagnosticArray,
            DiagnosticStatus=diagnostic.DiagnosticStatus,
            KeyValue=diagnostic.KeyValue,
            Header=std.Header,
            time=lambda t: stamp(*split_time(t)),
            level=level,
        )


# -- in --------------------------------------------------------------------------------------


def attribute_value(msg: Any) -> AttrValue:
    kind = int(msg.type)
    if kind == STRING:
        return str(msg.string_value)
    if kind == INTEGER:
        return int(msg.integer_value)
    if kind == DOUBLE:
        value = float(msg.double_value)
        if not math.isfinite(value):
            raise BridgeError(f"attribute {msg.key!r}: {value} is not a finite number")
        return value
    if kind == BOOL:
        return bool(msg.bool_value)
    raise BridgeError(f"attribute {msg.key!r}: type {kind} is not one of {_TYPE_NAMES}")


def attributes_from_msgs(msgs: Iterable[Any]) -> dict[str, AttrValue]:
    """Attributes of a message; an empty or repeated key, or a bad type, is an error naming it."""
    out: dict[str, AttrValue] = {}
    for msg in msgs:
        key = str(msg.key)
        if not key:
            raise BridgeError("attributes: a key is empty")
        if key in out:
            raise BridgeError(f"attributes: key {key!r} is given twice")
        out[key] = attribute_value(msg)
    return out


def request_from_msg(msg: Any) -> ServiceRequest:
    """What arrived on ~/publish or ~/unpublish."""
    return ServiceRequest(
        name=str(msg.name),
        type=str(msg.type),
        id=str(msg.id),
        url=str(msg.url),
        attributes=attributes_from_msgs(msg.attributes),
    )


# -- out -------------------------------------------------------------------------------------


def attribute_msg(m: Interfaces, key: str, value: AttrValue) -> Any:
    if isinstance(value, bool):
        return m.Attribute(key=key, type=BOOL, bool_value=value)
    if isinstance(value, int):
        return m.Attribute(key=key, type=INTEGER, integer_value=value)
    if isinstance(value, float):
        return m.Attribute(key=key, type=DOUBLE, double_value=value)
    return m.Attribute(key=key, type=STRING, string_value=str(value))


def attribute_msgs(m: Interfaces, attributes: Mapping[str, AttrValue]) -> list[Any]:
    return [attribute_msg(m, k, v) for k, v in sorted(attributes.items())]


def service_msg(m: Interfaces, s: Service) -> Any:
    return m.Service(
        id=s.id,
        name=s.name,
        type=s.type,
        url=s.url or "",
        attributes=attribute_msgs(m, s.attributes),
    )


def _nan(value: float | None) -> float:
    return math.nan if value is None else float(value)


def robot_msg(m: Interfaces, r: Robot) -> Any:
    return m.Robot(
        robot_id=r.robot_id,
        address=r.address,
        reachable=r.reachable,
        indicator=_nan(r.indicator),
        rtt_ms=_nan(r.rtt_ms),
        last_seen=m.time(r.last_seen),
        services=[service_msg(m, s) for s in r.services],
    )


def robot_msgs(m: Interfaces, robots: Sequence[Robot]) -> list[Any]:
    return [robot_msg(m, r) for r in robots]


def neighbor_list_msg(m: Interfaces, snapshot: Snapshot, robot_id: str) -> Any:
    return m.NeighborList(
        stamp=m.time(snapshot.stamp), robot_id=robot_id, robots=robot_msgs(m, snapshot.robots)
    )


def change_msg(m: Interfaces, c: Change) -> Any:
    msg = m.Change(stamp=m.time(c.stamp), kind=int(c.kind), robot_id=c.robot_id, address=c.address)
    if c.service is not None:
        msg.service = service_msg(m, c.service)
    return msg


def diagnostic_msg(m: Interfaces, d: Diagnosis, stamp: float) -> Any:
    status = m.DiagnosticStatus(
        level=m.level(int(d.level)),
        name=DIAGNOSTIC_NAME,
        message=d.message,
        hardware_id=d.robot_id,
        values=[m.KeyValue(key=k, value=v) for k, v in d.values],
    )
    return m.DiagnosticArray(header=m.Header(stamp=m.time(stamp)), status=[status])


def split_time(t: float) -> tuple[int, int]:
    """Seconds since the epoch as (seconds, nanoseconds)."""
    sec = math.floor(t)
    return sec, min(999_999_999, round((t - sec) * 1e9))
