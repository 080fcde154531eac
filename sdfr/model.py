"""Plain data shared by every layer: services and their validation."""

from __future__ import annotations

import hashlib
import json
import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

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


@dataclass(frozen=True, slots=True)
class Service:
    """One service a robot offers; `id` is assigned by the robot that owns it."""

    id: str
    name: str
    type: str
    url: str | None = None
    attributes: Mapping[str, AttrValue] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "name": self.name,
            "type": self.type,
            "url": self.url,
            "attributes": dict(self.attributes),
        }

    @classmethod
    def from_json(cls, obj: object, *, service_id: str | None = None) -> Service:
        """Validate a JSON object into a Service; raise ValidationError naming the field.

        With `service_id` the object needs no `id` (a new registration).
        """
        if not isinstance(obj, dict):
            raise ValidationError("body", "must be a JSON object")
        allowed = {"id", "name", "type", "url", "attributes"}
        unknown = sorted(set(obj) - allowed)
        if unknown:
            raise ValidationError(unknown[0], "unknown field")
        sid = service_id if service_id is not None else obj.get("id")
        if not isinstance(sid, str) or not SERVICE_ID_RE.fullmatch(sid):
            raise ValidationError("id", "must be 1-64 characters of A-Z a-z 0-9 . _ -")
        name = obj.get("name")
        if not isinstance(name, str) or not name.strip():
            raise ValidationError("name", "is required and must be a non-empty string")
        if len(name) > MAX_NAME:
            raise ValidationError("name", f"must be at most {MAX_NAME} characters")
        stype = obj.get("type")
        if not isinstance(stype, str) or not TYPE_RE.fullmatch(stype):
            raise ValidationError(
                "type",
                "is required: 1-128 characters of A-Z a-z 0-9 . _ : / -, starting with a "
                "letter or digit",
            )
        url = obj.get("url")
        if url is not None and (not isinstance(url, str) or len(url) > MAX_URL):
            raise ValidationError("url", f"must be a string of at most {MAX_URL} characters")
        attrs = obj.get("attributes", {})
        if attrs is None:
            attrs = {}
        if not isinstance(attrs, dict):
            raise ValidationError("attributes", "must be a JSON object")
        if len(attrs) > MAX_ATTRS:
            raise ValidationError("attributes", f"at most {MAX_ATTRS} attributes")
        clean: dict[str, AttrValue] = {}
        for key, value in attrs.items():
            where = f"attributes.{key}"
            if not key or len(key) > MAX_ATTR_KEY:
                raise ValidationError(where, f"keys must be 1-{MAX_ATTR_KEY} characters")
            if not isinstance(value, str | int | float | bool) or value is None:
                raise ValidationError(where, "values must be strings, numbers or booleans")
            if isinstance(value, str) and len(value) > MAX_ATTR_VALUE:
                raise ValidationError(where, f"at most {MAX_ATTR_VALUE} characters")
            if isinstance(value, float) and not math.isfinite(value):  # no JSON form
                raise ValidationError(where, "NaN and infinite numbers are not values")
            clean[key] = value
        return cls(id=sid, name=name, type=stype, url=url, attributes=clean)

    def matches(self, stype: str | None, attrs: Mapping[str, str]) -> bool:
        """True when the type matches and each attribute equals the given text."""
        if stype is not None and self.type != stype:
            return False
        for key, want in attrs.items():
            if key not in self.attributes:
                return False
            if attr_text(self.attributes[key]) != want:
                return False
        return True


def attr_text(value: AttrValue) -> str:
    """The text form a query string compares against (`true`, `3`, `0.5`, `abc`)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def canonical_json(services: Iterable[Service]) -> bytes:
    items = sorted((s.to_json() for s in services), key=lambda d: str(d["id"]))
    return json.dumps(items, sort_keys=True, separators=(",", ":")).encode()


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

    def shifted(self, offset: float) -> PeerRecord:
        """The same record with its times moved by `offset` seconds (core clock <-> epoch)."""
        return replace(self, first_seen=self.first_seen + offset, last_seen=self.last_seen + offset)

    def to_json(self) -> dict[str, Any]:
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
