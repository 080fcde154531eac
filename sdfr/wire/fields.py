"""What both forms of the datagram share when encoding: the field checks, the HOST value and
the JSON bodies of a set and of a delta."""

from collections import Counter
from collections.abc import Sequence
from typing import Literal

from sdfr.records.model import COMPACT_JSON, ROBOT_ID_RE, SERVICE_ID_RE, Service
from sdfr.wire.messages import (
    _BODY_CLOSE,
    _BODY_OPEN,
    MAX_BOOT_ID,
    MAX_ENCODED,
    MAX_FLEET,
    MAX_HOST,
    MAX_LOCATION,
    MAX_MAX_AGE,
    MAX_PARTS,
    MAX_VERSION,
    WANT_ALL,
    Origin,
    Update,
    _is_digest,
)


def _finish(head: bytes, body: bytes, kind: str) -> bytes:
    size = len(head) + len(body)
    if size > MAX_ENCODED:
        raise ValueError(f"{kind} would be {size} bytes, more than MAX_ENCODED ({MAX_ENCODED})")
    return head + body if body else head


def _service_json(service: Service) -> bytes:
    try:
        return service.json_text()
    except (ValueError, TypeError) as exc:  # NaN/inf, lone surrogates, non-JSON values
        raise ValueError(f"service {service.id!r} cannot be encoded as JSON: {exc}") from None


def _body(blobs: Sequence[bytes]) -> bytes:
    return _BODY_OPEN + b",".join(blobs) + _BODY_CLOSE


def _delta_body(msg: Update, *, compact: bool = False) -> bytes:
    """The delta's JSON body; `compact` leaves out an empty list."""
    if (msg.part, msg.parts) != (0, 1):
        raise ValueError("a delta Update is a single part (part 0 of 1)")
    if msg.base is None or not 0 <= msg.base < msg.origin.version:
        raise ValueError(f"delta base {msg.base} must be below version {msg.origin.version}")
    if len(set(msg.removed)) != len(msg.removed) or any(
        not SERVICE_ID_RE.fullmatch(r) for r in msg.removed
    ):
        raise ValueError(f"removed ids must be unique service ids: {msg.removed!r}")
    removed = COMPACT_JSON.encode(list(msg.removed)).encode()
    if compact and not msg.services:
        return b'{"removed":' + removed + b"}"
    full = _body([_service_json(s) for s in msg.services])
    if compact and not msg.removed:
        return full
    return full[:-1] + b',"removed":' + removed + b"}"


def _want_text(want: Literal["all"] | tuple[int, ...]) -> str:
    if want == WANT_ALL:
        return WANT_ALL
    if not isinstance(want, tuple) or not want:
        raise ValueError(f"want must be None, 'all' or a non-empty tuple of part indices: {want!r}")
    prev = -1
    for index in want:
        if type(index) is not int or not prev < index < MAX_PARTS + 1:
            raise ValueError(f"want must be sorted unique part indices 0..{MAX_PARTS}: {want!r}")
        prev = index
    return ",".join(map(str, want))


def _check_origin(origin: Origin) -> None:
    _check_range("fleet", origin.fleet, 0, MAX_FLEET)
    _check_range("wire", origin.wire, 1, 9)
    if not isinstance(origin.robot_id, str) or not ROBOT_ID_RE.fullmatch(origin.robot_id):
        raise ValueError(f"robot_id {origin.robot_id!r} does not match {ROBOT_ID_RE.pattern}")
    _check_range("boot_id", origin.boot_id, 0, MAX_BOOT_ID)
    _check_range("version", origin.version, 0, MAX_VERSION)
    if not _is_digest(origin.digest):
        raise ValueError(f"digest must be 16 lowercase hex characters: {origin.digest!r}")


def _check_range(name: str, value: int, lo: int, hi: int) -> None:
    if type(value) is not int or not lo <= value <= hi:
        raise ValueError(f"{name} must be an integer {lo}..{hi}, not {value!r}")


def _check_text(name: str, value: str) -> None:
    if not isinstance(value, str) or not value or value != value.strip():
        raise ValueError(f"{name} must be non-empty without surrounding whitespace: {value!r}")
    if not value.isprintable():
        raise ValueError(f"{name} must not contain control characters: {value!r}")


def _check_location(location: str) -> None:
    _check_text("LOCATION", location)
    if len(location.encode()) > MAX_LOCATION:
        raise ValueError(f"LOCATION is longer than {MAX_LOCATION} bytes: {location!r}")


def _check_max_age(max_age: int) -> None:
    _check_range("max_age", max_age, 1, MAX_MAX_AGE)


def _check_update_shape(part: int, parts: int) -> None:
    _check_range("parts", parts, 1, MAX_PARTS)
    _check_range("part", part, 0, parts - 1)


def _check_unique_ids(services: Sequence[Service]) -> None:
    if len({s.id for s in services}) != len(services):
        counts = Counter(s.id for s in services)
        dups = sorted(sid for sid, n in counts.items() if n > 1)
        raise ValueError(f"duplicate service ids: {', '.join(dups)}")


def _host(group: str, port: int) -> str:
    _check_range("port", port, 1, 65535)
    _check_text("group", group)
    if ":" in group and not group.startswith("["):
        group = f"[{group}]"
    host = f"{group}:{port}"
    if len(host) > MAX_HOST:
        raise ValueError(f"HOST {host!r} is longer than {MAX_HOST} characters")
    return host
