"""The discovery layer's status, as the API layer reads it: one typed, versioned record.

The discovery layer sends it as a datagram on STATE_DIR/status.sock when it changed (looked at
every STATUS_PERIOD, 5 s) and when the API layer asks (which it does before an answer shows
it), and writes it to STATE_DIR/discovery-status.json when it changed or every half a minute;
the API layer answers /health, /self, /metrics and /keys from it. `to_json` and
`DiscoveryStatus.from_json` are the only ways in and out: what one layer writes, the other
reads with the same field names and types. A record of another FORMAT, or one that does not
decode, reads as None (the discovery layer is then taken to be down).
"""

from __future__ import annotations

import dataclasses
import functools
import types
import typing
from dataclasses import dataclass, field
from typing import Any, TypeVar, get_args, get_origin

#: Bumped when a field changes meaning or type (adding one with a default needs no bump).
FORMAT = 1

T = TypeVar("T")


@dataclass(frozen=True, slots=True)
class Counters:
    datagrams_in: dict[str, int] = field(default_factory=dict)
    datagrams_out: dict[str, int] = field(default_factory=dict)
    bytes_in: int = 0
    bytes_out: int = 0
    rejects: dict[str, int] = field(default_factory=dict)
    challenges: int = 0
    challenges_limited: int = 0
    invites: int = 0


@dataclass(frozen=True, slots=True)
class AddressConflict:
    ip: str
    other_mac: str
    kept: bool
    phase: str


@dataclass(frozen=True, slots=True)
class Addressing:
    mode: str = "manual"
    state: str | None = None
    address: str | None = None
    #: the last few conflicts; `conflicts_total` counts every one since the layer started
    conflicts: tuple[AddressConflict, ...] = ()
    conflicts_total: int = 0


@dataclass(frozen=True, slots=True)
class UnknownKey:
    """Datagrams sealed with a key id the keyring does not hold, refused lately."""

    id: str
    #: the source address of the latest
    address: str
    count: int
    first_seen: float
    last_seen: float


@dataclass(frozen=True, slots=True)
class Auth:
    #: open (no key), accept, sign or enforce
    mode: str = "open"
    primary: str | None = None
    keys: tuple[str, ...] = ()
    #: datagrams verified, by key id
    received: dict[str, int] = field(default_factory=dict)
    ssdp_interop: bool = True
    #: key ids of refused seals heard within the miss window, the latest first
    unknown: tuple[UnknownKey, ...] = ()


@dataclass(frozen=True, slots=True)
class Describe:
    listening: str | None = None
    open: int = 0
    served: int = 0
    refused: int = 0


@dataclass(frozen=True, slots=True)
class Conflict:
    """Another sender claiming this robot's id."""

    address: str
    boot_id: int
    last_seen: float
    count: int


@dataclass(frozen=True, slots=True)
class Errors:
    #: callback failures in the last minute
    recent: int = 0
    last: str | None = None
    last_at: float | None = None
    #: a condition that lasts (the service set cannot be announced)
    persistent: str | None = None


@dataclass(frozen=True, slots=True)
class StateDir:
    writable: bool = True
    reason: str | None = None  # full, read-only or error
    error: str | None = None


@dataclass(frozen=True, slots=True)
class WifiStation:
    """A station of the fleet's WiFi that has not completed the key handshake with us."""

    mac: str
    seconds: float  # unauthorized this long


@dataclass(frozen=True, slots=True)
class Wifi:
    """The fleet's WiFi as this robot's radio sees it, when sdfrd joined it
    (`sdfr.host.wifiwatch`)."""

    iface: str
    ssid: str
    mode: str
    #: stations that completed the key handshake with this robot
    authorized: int = 0
    #: stations unauthorized for longer than the watch's grace
    refused: tuple[WifiStation, ...] = ()
    #: what an operator should do about `refused` (a /health warning), or None
    warning: str | None = None


@dataclass(frozen=True, slots=True)
class DiscoveryStatus:
    pid: int
    heartbeat: float
    #: The layer's thread (its kernel thread id) when it is a thread of sdfrd (`--layers
    #: threads`): a layer whose thread ended is down though its process runs on.
    thread: int | None = None
    #: True until the layer speaks on the fleet's network (its address bound, its
    #: description served, its core started): a layer alive but not yet discovering.
    starting: bool = False
    robot_id: str | None = None
    fleet: int = 0
    iface: str | None = None
    address: str = ""
    boot_id: int | None = None
    version: int | None = None
    started: float | None = None
    location: str | None = None
    peers_reachable: int = 0
    peers_known: int = 0
    addressing: Addressing = field(default_factory=Addressing)
    counters: Counters = field(default_factory=Counters)
    auth: Auth = field(default_factory=Auth)
    describe: Describe = field(default_factory=Describe)
    robot_id_conflict: Conflict | None = None
    errors: Errors = field(default_factory=Errors)
    state: StateDir = field(default_factory=StateDir)
    wifi: Wifi | None = None
    format: int = FORMAT

    def to_json(self) -> dict[str, object]:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, obj: object) -> DiscoveryStatus | None:
        """The record in `obj`, or None if it is not one (absent, damaged, another FORMAT)."""
        if not isinstance(obj, dict) or obj.get("format", FORMAT) != FORMAT:
            return None
        try:
            return decode(cls, obj)
        except (TypeError, ValueError, KeyError):
            return None


def decode(kind: type[T], obj: object) -> T:
    """`obj` (parsed JSON) as an instance of the dataclass `kind`, checking every field's
    type; unknown keys are ignored, missing ones take their defaults. TypeError if it does
    not fit."""
    return typing.cast(T, _value(kind, obj))


@functools.cache
def _fields(kind: type) -> tuple[tuple[str, Any], ...]:
    """A dataclass's (field name, resolved type) pairs: typing.get_type_hints compiles and
    evaluates every annotation, too slow to repeat for each record (it was the API layer's
    largest idle cost when done once a second)."""
    hints = typing.get_type_hints(kind)
    return tuple((f.name, hints[f.name]) for f in dataclasses.fields(kind))


def _value(hint: Any, obj: object) -> object:
    origin = get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        for arm in get_args(hint):
            try:
                return _value(arm, obj)
            except TypeError:
                continue
        raise TypeError(f"{obj!r} is none of {hint}")
    if hint is type(None):
        if obj is not None:
            raise TypeError(f"{obj!r} is not null")
        return None
    if dataclasses.is_dataclass(hint) and isinstance(hint, type):
        if not isinstance(obj, dict):
            raise TypeError(f"{hint.__name__} must be an object, not {obj!r}")
        values = {name: _value(kind, obj[name]) for name, kind in _fields(hint) if name in obj}
        return hint(**values)
    if origin is dict:
        key_type, value_type = get_args(hint)
        if not isinstance(obj, dict):
            raise TypeError(f"{obj!r} is not an object")
        return {_value(key_type, k): _value(value_type, v) for k, v in obj.items()}
    if origin is tuple:
        (item_type, _) = get_args(hint)
        if not isinstance(obj, list | tuple):
            raise TypeError(f"{obj!r} is not a list")
        return tuple(_value(item_type, v) for v in obj)
    if hint is float:
        if isinstance(obj, bool) or not isinstance(obj, int | float):
            raise TypeError(f"{obj!r} is not a number")
        return float(obj)
    if hint in (int, str, bool):
        if type(obj) is not hint:
            raise TypeError(f"{obj!r} is not a {hint.__name__}")
        return obj
    raise TypeError(f"cannot decode {hint}")
