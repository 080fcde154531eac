"""Plain data shared by every layer: services and their validation."""

from __future__ import annotations

import hashlib
import json
import re
import sys
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Annotated

import msgspec
from msgspec import Meta

from sdfr.errors import ValidationError

#: JSON scalar values an attribute may hold.
AttrValue = str | int | float | bool

ROBOT_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
SERVICE_ID_RE = re.compile(r"^[A-Za-z0-9._-]{1,64}$")
TYPE_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._:/-]{0,127}$")
MAX_NAME = 128
MAX_URL = 256
MAX_ATTRS = 32
MAX_ATTR_KEY = 64
MAX_ATTR_VALUE = 256


# -- the JSON form of a service: one typed model --------------------------------------------------
# Validation (`Service.from_json`, for the API, the store and what peers send) and the API's
# OpenAPI schemas (`sdfr.api.models`) are both made from these types: a limit is written here once.


def _whole(regex: re.Pattern[str]) -> str:
    """`regex` as a JSON Schema pattern that matches whole strings alike in Python (whose `$`
    also matches before a final newline) and in ECMA-262: `(?![\\s\\S])` is the very end."""
    return regex.pattern.removesuffix("$") + r"(?![\s\S])"


#: Control characters (C0, DEL, C1) and the Unicode line and paragraph separators: refused in
#: every text a user gives (names, URLs, attribute keys and values), since they forge log lines
#: and break tables.
CONTROL_CHARS = "\\x00-\\x1f\\x7f-\\x9f\\u2028\\u2029"
CONTROL_RE = re.compile(f"[{CONTROL_CHARS}]")
#: Text without control characters (the pattern matches whole strings, see `_whole`).
_PRINTABLE = f"^[^{CONTROL_CHARS}]*(?![\\s\\S])"

ServiceId = Annotated[str, Meta(pattern=_whole(SERVICE_ID_RE))]
ServiceName = Annotated[
    str,
    Meta(
        min_length=1,
        max_length=MAX_NAME,
        pattern=f"^[^{CONTROL_CHARS}]*[^{CONTROL_CHARS}\\s][^{CONTROL_CHARS}]*(?![\\s\\S])",
    ),
]
ServiceType = Annotated[
    str,
    Meta(
        pattern=_whole(TYPE_RE),
        description="What the service is, e.g. `camera/rgb`; searched by equality.",
    ),
]
ServiceUrl = Annotated[str, Meta(max_length=MAX_URL, pattern=_PRINTABLE)]
AttrKey = Annotated[str, Meta(min_length=1, max_length=MAX_ATTR_KEY, pattern=_PRINTABLE)]
#: A number with a JSON form (not NaN, not infinite).
AttrNumber = Annotated[float, Meta(ge=-sys.float_info.max, le=sys.float_info.max)]
AttrText = Annotated[str, Meta(max_length=MAX_ATTR_VALUE, pattern=_PRINTABLE)]
AttrJson = AttrText | int | AttrNumber | bool
Attributes = Annotated[
    dict[AttrKey, AttrJson],
    Meta(
        max_length=MAX_ATTRS,
        description="Capabilities, searched with `attr.KEY=VALUE`: a number matches by "
        "value (`30` finds 30 and 30.0), a boolean by `true`/`false`, text by equality.",
    ),
]


class ServiceInput(msgspec.Struct, forbid_unknown_fields=True):
    """A registration; one service must fit in one datagram."""

    name: ServiceName
    type: ServiceType
    id: (
        Annotated[
            ServiceId,
            Meta(
                description="Chosen by the client to make the publish idempotent: the same "
                "service again is a 200, another one under this id a 409. Left out, the robot "
                "picks one."
            ),
        ]
        | msgspec.UnsetType
    ) = msgspec.UNSET
    url: ServiceUrl | None = None
    attributes: Attributes | None = None


# msgspec builds a Struct type's decoding information the first time the type is used, and
# two threads using it for the first time at once can crash the process: a daemon died with
# SIGSEGV inside `msgspec.convert(..., ServiceInput)` when its API layer's first publish and
# its discovery layer's first decode of a peer's services came at the same moment. Build it
# here, once, under the import lock (tests/unit/sdfr/test_records_threads.py).
msgspec.json.Decoder(ServiceInput)


class ServiceOutput(msgspec.Struct, forbid_unknown_fields=True):
    """A service as the API and peers show it."""

    id: ServiceId
    name: ServiceName
    type: ServiceType
    url: ServiceUrl | None
    attributes: Attributes


#: What a field must be, said when it is not.
_RULES = {
    "id": "must be 1-64 characters of A-Z a-z 0-9 . _ -",
    "name": f"is required: 1-{MAX_NAME} characters, not all blank, no control characters",
    "type": "is required: 1-128 characters of A-Z a-z 0-9 . _ : / -, starting with a letter "
    "or digit",
    "url": f"must be a string of at most {MAX_URL} characters, without control characters",
    "attributes": f"must be a JSON object of at most {MAX_ATTRS} attributes",
}


def _invalid(exc: msgspec.ValidationError, obj: object) -> ValidationError:
    """msgspec's complaint as a ValidationError naming the field (`attributes.KEY` for one
    attribute)."""
    text = str(exc)
    if m := re.search(r"unknown field `(.+?)`", text):
        return ValidationError(m[1], "unknown field")
    if m := re.search(r"missing required field `(.+?)`", text):
        return ValidationError(m[1], _RULES.get(m[1], "is required"))
    m = re.search(r"`\$\.(\w+)", text)
    if m is None:
        return ValidationError("body", "must be a JSON object")
    field = m[1]
    attrs = obj.get("attributes") if isinstance(obj, dict) else None
    if field == "attributes" and isinstance(attrs, dict) and len(attrs) <= MAX_ATTRS:
        for key, value in attrs.items():
            where = f"attributes.{key}"
            try:
                msgspec.convert(key, AttrKey)
            except msgspec.ValidationError:
                return ValidationError(
                    where, f"keys must be 1-{MAX_ATTR_KEY} characters, without control characters"
                )
            try:
                msgspec.convert(value, AttrJson, strict=True)
            except msgspec.ValidationError:
                return ValidationError(
                    where,
                    f"values must be strings (at most {MAX_ATTR_VALUE} characters, without "
                    "control characters), numbers or booleans; NaN and infinite numbers are "
                    "not values",
                )
    return ValidationError(field, _RULES.get(field, text.split(" - at ")[0]))


@dataclass(frozen=True, slots=True)
class Service:
    """One service a robot offers; `id` is assigned by the robot that owns it."""

    id: str
    name: str
    type: str
    url: str | None = None
    attributes: Mapping[str, AttrValue] = field(default_factory=dict)
    # Its JSON, made once and kept (a service is replaced, never changed): every robot that
    # holds a set encodes it again at each change of it (its digest, a delta's dictionary,
    # the history map's row), and 70 services cost ~1 ms of CPU each time.
    _text: bytes | None = field(default=None, init=False, repr=False, compare=False)
    _canonical: bytes | None = field(default=None, init=False, repr=False, compare=False)

    def to_json(self) -> dict[str, object]:
        return {
            "id": self.id,
            "name": self.name,
            "type": self.type,
            "url": self.url,
            "attributes": dict(self.attributes),
        }

    def json_text(self) -> bytes:
        """`to_json` as compact UTF-8 JSON in its keys' order (the store's rows, a delta's
        dictionary, the wire)."""
        text = self._text
        if text is None:
            text = COMPACT_JSON.encode(self.to_json()).encode()
            object.__setattr__(self, "_text", text)
        return text

    def canonical(self) -> bytes:
        """`to_json` as the digest hashes it: keys sorted, ASCII only."""
        text = self._canonical
        if text is None:
            text = _CANONICAL.encode(self.to_json()).encode()
            object.__setattr__(self, "_canonical", text)
        return text

    @classmethod
    def from_json(cls, obj: object, *, service_id: str | None = None) -> Service:
        """Validate a JSON object into a Service (by `ServiceInput`); raise ValidationError
        naming the field.  With `service_id` the object needs no `id` (a new registration)."""
        try:
            parsed = msgspec.convert(obj, ServiceInput, strict=True)
        except msgspec.ValidationError as exc:
            raise _invalid(exc, obj) from None
        sid = service_id if service_id is not None else parsed.id
        if isinstance(sid, msgspec.UnsetType):
            raise ValidationError("id", _RULES["id"])
        return cls(
            id=sid,
            name=parsed.name,
            type=parsed.type,
            url=parsed.url,
            attributes=parsed.attributes or {},
        )

    def matches(self, stype: str | None, attrs: Mapping[str, str]) -> bool:
        """True when the type matches and each attribute matches the given text (see
        `attr_matches`)."""
        if stype is not None and self.type != stype:
            return False
        for key, want in attrs.items():
            if key not in self.attributes:
                return False
            if not attr_matches(self.attributes[key], want):
                return False
        return True


def attr_matches(value: AttrValue, text: str) -> bool:
    """Whether an attribute's value matches a search's text, the query string's `VALUE`:

    - a boolean matches `true` or `false` (any case), and nothing else (not `1`);
    - a number matches a text that reads as the same number (`30`, `30.0`, `3e1` all find
      30 and 30.0); `NaN` and infinities match nothing;
    - a string matches the same text exactly (`"30"` is found by `30`, `"True"` by `True`).
    """
    if isinstance(value, bool):
        return text.lower() == ("true" if value else "false")
    if isinstance(value, int | float):
        if text != text.strip():
            return False
        try:
            if isinstance(value, int) and re.fullmatch(r"[+-]?[0-9]+", text):
                return int(text) == value  # exact, also past float's 53 bits
            return float(text) == value
        except ValueError:
            return False
    return value == text


def attr_text(value: AttrValue) -> str:
    """The text form a query string compares against (`true`, `3`, `0.5`, `abc`)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


#: Compact UTF-8 JSON without NaN or infinities: a service's text, and the wire's JSON.
COMPACT_JSON = json.JSONEncoder(ensure_ascii=False, allow_nan=False, separators=(",", ":"))
_CANONICAL = json.JSONEncoder(sort_keys=True, separators=(",", ":"))


def canonical_json(services: Iterable[Service]) -> bytes:
    """The set as its digest hashes it: a JSON array of its services by id, keys sorted."""
    return b"[" + b",".join(s.canonical() for s in sorted(services, key=by_id)) + b"]"


def json_array(services: Iterable[Service]) -> bytes:
    """The services as a compact UTF-8 JSON array, in their order (`Service.json_text`)."""
    return b"[" + b",".join(s.json_text() for s in services) + b"]"


def by_id(service: Service) -> str:
    """A service's sort key in a set: its id."""
    return service.id


def service_digest(services: Iterable[Service]) -> str:
    """A short fingerprint of a service set, the same on every robot for the same set."""
    return hashlib.sha256(canonical_json(services)).hexdigest()[:16]


def check_robot_id(robot_id: str) -> str:
    if not ROBOT_ID_RE.fullmatch(robot_id):
        raise ValidationError(
            "robot_id", "must be 1-64 characters of A-Z a-z 0-9 . _ -, starting alphanumeric"
        )
    return robot_id


@dataclass(frozen=True, slots=True)
class PeerRecord:
    """A robot of the history map: what the protocol core hands out (times on the core's
    clock) and the store keeps (times shifted to Unix epoch, `shifted`)."""

    robot_id: str
    address: str
    location: str
    boot_id: int
    version: int
    digest: str
    reachable: bool
    first_seen: float
    last_seen: float
    indicator: float | None
    rtt_ms: float | None
    pings: int
    services: tuple[Service, ...] = field(default=())
    #: It said Byebye for its current boot (not kept in the store: only the discovery layer's
    #: changes feed, which tells "left" from "unreachable", needs it).
    departed: bool = False

    def shifted(self, offset: float) -> PeerRecord:
        """The same record with its times moved by `offset` seconds (core clock <-> epoch)."""
        return replace(self, first_seen=self.first_seen + offset, last_seen=self.last_seen + offset)

    def to_json(self) -> dict[str, object]:
        return {
            "robot_id": self.robot_id,
            "address": self.address,
            "location": self.location,
            "reachable": self.reachable,
            "indicator": self.indicator,
            "rtt_ms": self.rtt_ms,
            "boot_id": self.boot_id,
            "version": self.version,
            "first_seen": self.first_seen,
            "last_seen": self.last_seen,
            "services": [s.to_json() for s in self.services],
        }
