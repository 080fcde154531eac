"""The wire codec: SSDP-style UDP datagrams to typed messages and back.

No I/O and no clock: `encode` turns a message into the bytes of one datagram, `decode` turns the
bytes of one datagram into a message or a `Reject` saying why not.  The format follows UPnP Device
Architecture 2.0 section 1.3 (SSDP): an HTTP-style start line, `NAME: value` header lines, a blank
line and, for `Update` only, a JSON body.  SDfR's own fields travel in `X-SDFR-*` headers, so
standard SSDP clients see an SDfR robot as an ordinary root device answering their searches.
"""

from __future__ import annotations

import ipaddress
import json
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache, lru_cache
from typing import Literal, NoReturn, TypeAlias

from sdfr import __version__
from sdfr.errors import ValidationError
from sdfr.model import ROBOT_ID_RE, SERVICE_ID_RE, Service

__all__ = [
    "DEFAULT_GROUP",
    "DEFAULT_PORT",
    "DEVICE_TYPE",
    "MAX_DATAGRAM",
    "MAX_ENCODED",
    "MESSAGE_TYPES",
    "REJECT_REASONS",
    "SEAL_RESERVE",
    "SERVER",
    "WANT_ALL",
    "Alive",
    "Byebye",
    "Discovery",
    "Message",
    "Origin",
    "Reject",
    "Response",
    "Update",
    "Want",
    "check_service_fits",
    "decode",
    "encode",
    "encode_update_parts",
    "fleet_target",
    "max_service_json_bytes",
    "parts_needed",
    "service_json_size",
]

#: Largest UDP payload SDfR sends or accepts (no IP fragmentation on radio links).
MAX_DATAGRAM = 1400
#: Room every encoded datagram leaves for a seal (sdfr.auth): a keyed fleet then has exactly the
#: limits of an open one, and a service accepted before a key was set still fits after.
SEAL_RESERVE = 64
#: Largest datagram `encode` and `encode_update_parts` produce.
MAX_ENCODED = MAX_DATAGRAM - SEAL_RESERVE
DEFAULT_GROUP = "239.255.255.250"
DEFAULT_PORT = 1900
DEVICE_TYPE = "urn:sdfr-org:device:robot:1"
SERVER = f"Linux UPnP/1.1 SDfR/{__version__}"

MAX_FLEET = 255
MAX_BOOT_ID = 2**31 - 1
MAX_VERSION = 2**53
MAX_SEQ = 2**53
MAX_PARTS = 255
MAX_MAX_AGE = 86400
#: Longest LOCATION, in UTF-8 bytes when encoding (characters when decoding).
MAX_LOCATION = 200
#: Longest `HOST` value (`group:port`): a bracketed full IPv6 address with a 5-digit port.
MAX_HOST = 47
#: Largest MX encoded, and what larger accepted values are clamped to when decoding.
MAX_MX = 5
#: Largest MX decode accepts at all.
MAX_MX_ACCEPTED = 120
CONFIGID_MODULUS = 2**24


def fleet_target(fleet: int) -> str:
    """The NT / search target naming one fleet."""
    return f"urn:sdfr-org:fleet:{fleet}"


def usn(robot_id: str) -> str:
    """The USN a robot announces itself with."""
    return f"uuid:{robot_id}::{DEVICE_TYPE}"


@dataclass(frozen=True, slots=True)
class Origin:
    """Who sent an SDfR message."""

    fleet: int  # 0..255, X-SDFR-FLEET
    robot_id: str  # sdfr.model.ROBOT_ID_RE, X-SDFR-ROBOT
    boot_id: int  # BOOTID.UPNP.ORG, 0 .. 2**31-1
    version: int  # X-SDFR-VERSION, 0 .. 2**53; CONFIGID.UPNP.ORG carries version % 2**24
    digest: str  # X-SDFR-DIGEST, 16 lowercase hex chars (sdfr.model.service_digest)


WANT_ALL: Literal["all"] = "all"
#: Update parts a searcher wants back: none, all, or sorted unique 0-based indices below 256.
Want: TypeAlias = Literal["all"] | tuple[int, ...] | None


@dataclass(frozen=True, slots=True)
class Discovery:
    """`M-SEARCH * HTTP/1.1`: a search, or with `seq` a unicast ping."""

    origin: Origin | None  # None: a plain SSDP client (no X-SDFR-* headers)
    st: str
    mx: int  # decode accepts 0..120 and clamps to 5; a missing MX decodes as 0
    seq: int | None = None
    want: Want = None
    want_version: int | None = None
    # encode: HOST is group:port, which must be a multicast address iff this is True;
    # decode: True iff MAN is present and HOST is a multicast address (or the given group).
    multicast: bool = True


@dataclass(frozen=True, slots=True)
class Response:
    """`HTTP/1.1 200 OK`: the SSDP search response, also the unicast ping reply.

    A ping reply (`seq` set) to an SDfR robot may leave `location` empty and `max_age` 0: it
    then goes without the SSDP lines only a UPnP control point needs (CACHE-CONTROL, EXT,
    LOCATION, SERVER, USN), about 150 bytes less, since the pinger knows the robot already.
    A ping reply may carry the replier's own ping to the pinger (`ping`, X-SDFR-PING), which
    is answered by a reply with that sequence number: three datagrams give both robots a
    round trip, where two pings and two replies would take four.
    """

    origin: Origin
    st: str
    location: str
    max_age: int
    seq: int | None = None
    ping: int | None = None


@dataclass(frozen=True, slots=True)
class Update:
    """`NOTIFY` with `NTS: ssdp:update`: one part of a robot's service set."""

    origin: Origin
    location: str
    max_age: int
    part: int  # 0-based
    parts: int  # 1..255; on the wire X-SDFR-PART is "<part+1>/<parts>"
    services: tuple[Service, ...]
    #: A delta (always one part): the set of version `base` with `removed` ids taken out and
    #: `services` added or replaced gives the set of `origin.version`. None: a whole set's part.
    base: int | None = None
    removed: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class Alive:
    """`NOTIFY` with `NTS: ssdp:alive`: the beacon, no body."""

    origin: Origin
    location: str
    max_age: int


@dataclass(frozen=True, slots=True)
class Byebye:
    """`NOTIFY` with `NTS: ssdp:byebye`."""

    origin: Origin


@dataclass(frozen=True, slots=True)
class Reject:
    """What `decode` returns for a datagram it will not accept."""

    reason: str  # one of REJECT_REASONS
    detail: str


REJECT_REASONS = (
    "too-large",
    "bad-start-line",
    "bad-header",
    "missing-header",
    "bad-value",
    "bad-body",
    "not-sdfr",
    "other-fleet",
    "unsupported",
)

Message: TypeAlias = Discovery | Response | Update | Alive | Byebye
#: The message types' names, as counters and metrics label them.
MESSAGE_TYPES = ("discovery", "response", "update", "alive", "byebye")

_MSEARCH_LINE = "M-SEARCH * HTTP/1.1"
_NOTIFY_LINE = "NOTIFY * HTTP/1.1"
_OK_LINE = "HTTP/1.1 200 OK"
_MAN = '"ssdp:discover"'
_NTS_TYPE = {"ssdp:alive": "alive", "ssdp:update": "update", "ssdp:byebye": "byebye"}
_HEX = "0123456789abcdef"
_BODY_OPEN = b'{"services":['
_BODY_CLOSE = b"]}"
_BODY_WRAP = len(_BODY_OPEN) + len(_BODY_CLOSE)

_JSON_ENCODER = json.JSONEncoder(ensure_ascii=False, allow_nan=False, separators=(",", ":"))


def _no_constant(name: str) -> NoReturn:
    raise ValueError(f"{name} is not JSON")


_JSON_DECODER = json.JSONDecoder(parse_constant=_no_constant)


# --------------------------------------------------------------------------------------------
# Encoding


def encode(msg: Message, *, group: str = DEFAULT_GROUP, port: int = DEFAULT_PORT) -> bytes:
    """The datagram for `msg`; ValueError if a field is out of range or it exceeds MAX_ENCODED.

    `group` and `port` fill the HOST header of M-SEARCH and NOTIFY (for a unicast search pass the
    peer's address and `multicast=False`).
    """
    if isinstance(msg, Update):
        _check_update_shape(msg.part, msg.parts)
        blobs = [_service_json(s) for s in msg.services]
        _check_unique_ids(msg.services)
        prefix = _update_prefix(msg.origin, msg.location, msg.max_age, _host(group, port))
        if msg.base is not None:
            body = _delta_body(msg)
            prefix += f"X-SDFR-BASE: {msg.base}\r\n".encode()
        else:
            if msg.removed:
                raise ValueError("removed ids belong to a delta Update (base is None)")
            body = _body(blobs)
        suffix = _update_suffix(str(msg.part + 1), str(msg.parts), str(len(body)))
        return _finish(prefix + suffix, body, "Update")
    if isinstance(msg, Discovery):
        lines = _discovery_lines(msg, group, port)
    elif isinstance(msg, Response):
        lines = _response_lines(msg)
    elif isinstance(msg, Alive):
        _check_location(msg.location)
        _check_max_age(msg.max_age)
        lines = _notify_lines(msg.origin, "alive", _host(group, port))
        lines.insert(2, f"LOCATION: {msg.location}")
        lines.insert(2, f"CACHE-CONTROL: max-age={msg.max_age}")
    elif isinstance(msg, Byebye):
        lines = _notify_lines(msg.origin, "byebye", _host(group, port))
    else:
        raise TypeError(f"not an SDfR message: {type(msg).__name__}")
    lines.append("\r\n")
    return _finish("\r\n".join(lines).encode(), b"", type(msg).__name__)


def encode_update_parts(
    origin: Origin,
    location: str,
    max_age: int,
    services: Sequence[Service],
    *,
    group: str = DEFAULT_GROUP,
    port: int = DEFAULT_PORT,
) -> list[bytes]:
    """Split a whole service set into as few Update datagrams as greedy packing allows.

    Parts are numbered 0..n-1 with the same total, each at most MAX_ENCODED bytes, and keep the
    order of `services`; an empty set is one part with no services.  ValueError when a single
    service cannot fit in a datagram alone, ids repeat, or the set needs more than 255 parts.
    """
    prefix = _update_prefix(origin, location, max_age, _host(group, port))
    _check_unique_ids(services)
    blobs = [_service_json(s) for s in services]
    sizes = [len(b) for b in blobs]
    ids = [s.id for s in services]

    # The header grows with the digits of the part total.  Start from a lower bound of the total
    # (so the digits only ever grow and end exact): one packing pass is the rule.
    fixed = len(prefix) + len(_update_suffix("", "", ""))
    room = MAX_ENCODED - fixed - 1 - 1 - 2 - _BODY_WRAP  # most body one part could hold
    estimate = max(1, -(-sum(sizes) // room)) if room > 0 else 1
    digits = len(str(estimate))
    while True:
        groups = _pack(sizes, ids, fixed + digits)
        if len(groups) > MAX_PARTS:
            raise ValueError(
                f"{len(services)} services need {len(groups)} update parts, more than {MAX_PARTS}"
            )
        if len(str(len(groups))) <= digits:
            break
        digits = len(str(len(groups)))

    total = str(len(groups))
    out: list[bytes] = []
    for i, (start, stop) in enumerate(groups):
        body = _body(blobs[start:stop])
        suffix = _update_suffix(str(i + 1), total, str(len(body)))
        out.append(_finish(prefix + suffix, body, "Update"))
    return out


def _pack(sizes: Sequence[int], ids: Sequence[str], fixed: int) -> list[tuple[int, int]]:
    """Greedy packing: (start, stop) slices of services whose compact JSON has `sizes`, given
    `fixed`, the header bytes apart from the digits of the part number and of the content
    length.  ValueError naming the service (from `ids`) that cannot fit a datagram alone."""
    groups: list[tuple[int, int]] = []
    start = 0
    body = _BODY_WRAP  # body bytes of the current part so far
    part_digits = 1
    for i, size in enumerate(sizes):
        grown = body + size + (1 if i > start else 0)
        if fixed + part_digits + len(str(grown)) + grown <= MAX_ENCODED:
            body = grown
            continue
        if i > start:  # close the current part and retry this service in a fresh one
            groups.append((start, i))
            start = i
            part_digits = len(str(len(groups) + 1))
            grown = _BODY_WRAP + size
            if fixed + part_digits + len(str(grown)) + grown <= MAX_ENCODED:
                body = grown
                continue
        room = MAX_ENCODED - fixed - part_digits - 4 - _BODY_WRAP
        raise ValueError(
            f"service {ids[i]!r} is {size} bytes of JSON; at most {room} fit in "
            f"one update datagram ({MAX_ENCODED} bytes) with these headers"
        )
    groups.append((start, len(sizes)))
    return groups


@lru_cache(maxsize=64)
def _worst_fixed(robot_id: str = "r" * 64, location_len: int = MAX_LOCATION) -> int:
    """Update header bytes with the longest headers (by default a 64-character robot id and a
    200-byte location; part 255/255, the longest HOST and numbers), apart from the part
    number and content length."""
    origin = Origin(MAX_FLEET, robot_id, MAX_BOOT_ID, 2**53 - 1, "f" * 16)
    prefix = _update_prefix(origin, "l" * location_len, MAX_MAX_AGE, "h" * MAX_HOST)
    return len(prefix) + len(_update_suffix("", str(MAX_PARTS), ""))


def service_json_size(service: Service) -> int:
    """Bytes of `service`'s compact JSON in an Update (ValueError if it has no JSON form)."""
    return len(_service_json(service))


def parts_needed(
    sizes: Sequence[int], *, robot_id: str | None = None, location_len: int = MAX_LOCATION
) -> int:
    """Update parts a set of services whose JSON has these sizes needs with the longest
    headers robot `robot_id` (any robot, by default) can send with a location of at most
    `location_len` bytes: its set can be announced iff this is <= MAX_PARTS.
    ValueError if one of them cannot fit a datagram alone."""
    fixed = _worst_fixed("r" * 64 if robot_id is None else robot_id, location_len)
    return len(_pack(sizes, [f"#{i}" for i in range(len(sizes))], fixed))


@cache
def max_service_json_bytes() -> int:
    """The largest compact service JSON that fits alone in one Update with the longest headers
    (64-character robot id, 200-byte location, part 255/255, longest HOST and numbers)."""
    fixed = _worst_fixed() + len(str(MAX_PARTS))
    size = MAX_ENCODED - fixed - _BODY_WRAP
    while fixed + len(str(size + _BODY_WRAP)) + size + _BODY_WRAP > MAX_ENCODED:
        size -= 1
    return size


def check_service_fits(service: Service) -> None:
    """Raise ValidationError("service", ...) unless `service` fits alone in one Update."""
    try:
        size = len(_service_json(service))
    except ValueError as exc:
        raise ValidationError("service", str(exc)) from None
    limit = max_service_json_bytes()
    if size > limit:
        raise ValidationError(
            "service",
            f"is {size} bytes as JSON, more than the {limit} bytes that fit in one discovery "
            f"datagram; shorten the name, url or attributes",
        )


def _finish(head: bytes, body: bytes, kind: str) -> bytes:
    size = len(head) + len(body)
    if size > MAX_ENCODED:
        raise ValueError(f"{kind} would be {size} bytes, more than MAX_ENCODED ({MAX_ENCODED})")
    return head + body if body else head


def _service_json(service: Service) -> bytes:
    try:
        return _JSON_ENCODER.encode(service.to_json()).encode()
    except (ValueError, TypeError) as exc:  # NaN/inf, lone surrogates, non-JSON values
        raise ValueError(f"service {service.id!r} cannot be encoded as JSON: {exc}") from None


def _body(blobs: Sequence[bytes]) -> bytes:
    return _BODY_OPEN + b",".join(blobs) + _BODY_CLOSE


def _delta_body(msg: Update) -> bytes:
    if (msg.part, msg.parts) != (0, 1):
        raise ValueError("a delta Update is a single part (part 0 of 1)")
    if msg.base is None or not 0 <= msg.base < msg.origin.version:
        raise ValueError(f"delta base {msg.base} must be below version {msg.origin.version}")
    if len(set(msg.removed)) != len(msg.removed) or any(
        not SERVICE_ID_RE.fullmatch(r) for r in msg.removed
    ):
        raise ValueError(f"removed ids must be unique service ids: {msg.removed!r}")
    removed = _JSON_ENCODER.encode(list(msg.removed)).encode()
    return _body([_service_json(s) for s in msg.services])[:-1] + b',"removed":' + removed + b"}"


def _origin_lines(origin: Origin, kind: str) -> list[str]:
    _check_origin(origin)
    return [
        f"BOOTID.UPNP.ORG: {origin.boot_id}",
        f"CONFIGID.UPNP.ORG: {origin.version % CONFIGID_MODULUS}",
        f"X-SDFR-FLEET: {origin.fleet}",
        f"X-SDFR-ROBOT: {origin.robot_id}",
        f"X-SDFR-TYPE: {kind}",
        f"X-SDFR-VERSION: {origin.version}",
        f"X-SDFR-DIGEST: {origin.digest}",
    ]


def _notify_lines(origin: Origin, kind: str, host: str) -> list[str]:
    lines = [
        _NOTIFY_LINE,
        f"HOST: {host}",
        f"NT: {fleet_target(origin.fleet)}",
        f"NTS: ssdp:{kind}",
        f"SERVER: {SERVER}",
        f"USN: {usn(origin.robot_id)}",
    ]
    lines += _origin_lines(origin, kind)
    return lines


def _update_prefix(origin: Origin, location: str, max_age: int, host: str) -> bytes:
    """The Update header lines up to X-SDFR-PART, which `_update_suffix` adds."""
    _check_location(location)
    _check_max_age(max_age)
    lines = _notify_lines(origin, "update", host)
    lines.insert(2, f"LOCATION: {location}")
    lines.insert(2, f"CACHE-CONTROL: max-age={max_age}")
    lines.append("")
    return "\r\n".join(lines).encode()


def _update_suffix(part: str, parts: str, content_length: str) -> bytes:
    """The last Update header lines; their length is a constant plus the lengths of the three
    ASCII texts, which `encode_update_parts` relies on."""
    return (
        f"X-SDFR-PART: {part}/{parts}\r\nCONTENT-TYPE: application/json\r\n"
        f"CONTENT-LENGTH: {content_length}\r\n\r\n"
    ).encode()


def _discovery_lines(msg: Discovery, group: str, port: int) -> list[str]:
    host = _host(group, port)
    if msg.multicast != _is_multicast(group):
        raise ValueError(
            f"HOST {group!r} is {'not ' if msg.multicast else ''}a multicast address but "
            f"multicast={msg.multicast}; a unicast search takes the peer's address as group="
        )
    _check_text("ST", msg.st)
    if not 0 <= msg.mx <= MAX_MX:
        raise ValueError(f"MX must be 0..{MAX_MX}, not {msg.mx}")
    lines = [_MSEARCH_LINE, f"HOST: {host}", f"MAN: {_MAN}"]
    if msg.multicast or msg.mx:
        lines.append(f"MX: {msg.mx}")
    lines.append(f"ST: {msg.st}")
    if msg.origin is None:
        if msg.seq is not None or msg.want is not None or msg.want_version is not None:
            raise ValueError("seq, want and want_version need an origin (X-SDFR-* headers)")
        return lines
    lines += _origin_lines(msg.origin, "discovery")
    if msg.seq is not None:
        _check_range("seq", msg.seq, 0, MAX_SEQ)
        lines.append(f"X-SDFR-SEQ: {msg.seq}")
    if msg.want is not None:
        lines.append(f"X-SDFR-WANT: {_want_text(msg.want)}")
    if msg.want_version is not None:
        _check_range("want_version", msg.want_version, 0, MAX_VERSION)
        lines.append(f"X-SDFR-WANT-VERSION: {msg.want_version}")
    return lines


def _response_lines(msg: Response) -> list[str]:
    _check_text("ST", msg.st)
    ping = []
    if msg.ping is not None:
        if msg.seq is None:
            raise ValueError("only a ping reply (seq) can carry a ping")
        _check_range("ping", msg.ping, 0, MAX_SEQ)
        ping = [f"X-SDFR-PING: {msg.ping}"]
    if not msg.location and msg.seq is not None:  # a compact ping reply
        if msg.max_age:
            raise ValueError("a ping reply without LOCATION has max_age 0")
        _check_range("seq", msg.seq, 0, MAX_SEQ)
        return [_OK_LINE, f"ST: {msg.st}", *_origin_lines(msg.origin, "response"),
                f"X-SDFR-SEQ: {msg.seq}", *ping]  # fmt: skip
    _check_location(msg.location)
    _check_max_age(msg.max_age)
    lines = [
        _OK_LINE,
        f"CACHE-CONTROL: max-age={msg.max_age}",
        "EXT:",
        f"LOCATION: {msg.location}",
        f"SERVER: {SERVER}",
        f"ST: {msg.st}",
        f"USN: {usn(msg.origin.robot_id)}",
    ]
    lines += _origin_lines(msg.origin, "response")
    if msg.seq is not None:
        _check_range("seq", msg.seq, 0, MAX_SEQ)
        lines.append(f"X-SDFR-SEQ: {msg.seq}")
    return lines + ping


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


@lru_cache(maxsize=256)
def _is_multicast(host: str) -> bool:
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    try:
        return ipaddress.ip_address(host).is_multicast
    except ValueError:
        return False


def _is_digest(value: str) -> bool:
    return isinstance(value, str) and len(value) == 16 and not value.strip(_HEX)


# --------------------------------------------------------------------------------------------
# Decoding


class _Rejected(Exception):
    """Raised inside the decoder, turned into a Reject by `decode`."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(reason, detail)
        self.reason = reason
        self.detail = detail


def decode(data: bytes, *, fleet: int | None = None, group: str | None = None) -> Message | Reject:
    """The message in one datagram, or a Reject saying why not.  Never raises.

    With `fleet`, SDfR messages of other fleets are rejected ("other-fleet") before anything but
    the fleet header is parsed.  `group` only feeds `Discovery.multicast`: HOST must equal it (by
    default HOST must be any multicast address).
    """
    try:
        return _decode(data, fleet, group)
    except _Rejected as rej:
        return Reject(rej.reason, rej.detail)
    except Exception as exc:  # a bug, but decode must not take the receive loop down
        return Reject("bad-value", f"internal error: {type(exc).__name__}: {exc}")


_FLEET_NEEDLE = b"\nX-SDFR-FLEET:"


def _decode(data: bytes, fleet: int | None, group: str | None) -> Message | Reject:
    size = len(data)
    if size > MAX_DATAGRAM:
        raise _Rejected("too-large", f"{size} bytes, more than {MAX_DATAGRAM}")

    # Head and body: the first blank line, CRLF or bare LF; without one the whole datagram is head.
    end = data.find(b"\r\n\r\n")
    bare = data.find(b"\n\n", 0, end if end >= 0 else size)
    if bare >= 0:
        end, body_start = bare, bare + 2
    elif end >= 0:
        body_start = end + 4
    else:
        end = body_start = size

    if fleet is not None:  # the cheap filter, on raw bytes, for our own header spelling
        at = data.find(_FLEET_NEEDLE, 0, end)
        if at >= 0:
            stop = data.find(b"\n", at + len(_FLEET_NEEDLE), end)
            raw = data[at + len(_FLEET_NEEDLE) : stop if stop >= 0 else end].strip()
            if 0 < len(raw) <= 3 and raw.isdigit() and int(raw) != fleet:
                return Reject("other-fleet", f"fleet {int(raw)}, not {fleet}")

    raw_head = data[:end]
    try:
        head = raw_head.decode()
    except UnicodeDecodeError:
        head = raw_head.decode("latin-1")
    lines = head.split("\n")
    if body_start == size and end == size:  # no blank line: tolerate a trailing line ending
        while len(lines) > 1 and not lines[-1].strip():
            lines.pop()
    start = lines[0].strip()
    if start == _MSEARCH_LINE:
        method = "M-SEARCH"
    elif start == _NOTIFY_LINE:
        method = "NOTIFY"
    else:
        status = start[9:12] if start.startswith("HTTP/1.1 ") else ""
        if len(status) != 3 or not status.isascii() or not status.isdigit():
            raise _Rejected("bad-start-line", repr(start[:80]))
        if start[12:13] not in ("", " "):
            raise _Rejected("bad-start-line", repr(start[:80]))
        if status != "200":
            raise _Rejected("unsupported", f"status {status}")
        method = "200"

    headers: dict[str, str] = {}
    setdefault = headers.setdefault
    for i in range(1, len(lines)):
        name, colon, value = lines[i].partition(":")
        key = name.strip().upper()
        if not colon or not key or " " in key or "\t" in key:
            raise _Rejected("bad-header", f"not a header line: {lines[i][:80]!r}")
        value = value.strip()
        if setdefault(key, value) != value:
            raise _Rejected("bad-header", f"{key} given twice with different values")
    sdfr = "X-SDFR-TYPE" in headers or any(key[:7] == "X-SDFR-" for key in headers)

    if fleet is not None and sdfr:  # other spellings of the fleet header
        text = headers.get("X-SDFR-FLEET")
        if text is not None:
            got = _parse_int(text, 0, MAX_FLEET)
            if got is not None and got != fleet:
                return Reject("other-fleet", f"fleet {got}, not {fleet}")

    if method == "M-SEARCH":
        return _decode_search(headers, sdfr, group)
    if not sdfr:
        raise _Rejected("not-sdfr", f"{start[:20]} without X-SDFR-* headers")
    if method == "NOTIFY":
        return _decode_notify(headers, data[body_start:])
    return _decode_response(headers)


def _decode_search(headers: dict[str, str], sdfr: bool, group: str | None) -> Discovery:
    man = headers.get("MAN")
    if man is not None and man != _MAN and man != "ssdp:discover":
        raise _Rejected("bad-value", f'MAN must be "ssdp:discover", not {man[:80]!r}')
    st = _need(headers, "ST")
    if not st:
        raise _Rejected("bad-value", "ST is empty")
    mx_text = headers.get("MX")
    mx = 0 if mx_text is None else _int_value("MX", mx_text, 0, MAX_MX_ACCEPTED)
    if mx > MAX_MX:
        mx = MAX_MX
    multicast = False
    if man is not None:
        host = _host_only(headers.get("HOST", ""))
        multicast = host == group if group is not None else _is_multicast(host)
    if not sdfr:
        return Discovery(None, st, mx, multicast=multicast)
    origin = _decode_origin(headers, "discovery")
    seq = _optional_int(headers, "X-SDFR-SEQ", MAX_SEQ)
    want_text = headers.get("X-SDFR-WANT")
    want = None if want_text is None else _parse_want(want_text)
    want_version = _optional_int(headers, "X-SDFR-WANT-VERSION", MAX_VERSION)
    return Discovery(origin, st, mx, seq, want, want_version, multicast)


def _decode_response(headers: dict[str, str]) -> Response:
    origin = _decode_origin(headers, "response")
    _check_usn(headers, origin)
    st = _need(headers, "ST")
    if not st:
        raise _Rejected("bad-value", "ST is empty")
    seq = _optional_int(headers, "X-SDFR-SEQ", MAX_SEQ)
    ping = _optional_int(headers, "X-SDFR-PING", MAX_SEQ)
    if ping is not None and seq is None:
        raise _Rejected("bad-value", "X-SDFR-PING on a response that answers no ping")
    if seq is not None and "LOCATION" not in headers and "CACHE-CONTROL" not in headers:
        return Response(origin, st, "", 0, seq, ping)  # a compact ping reply
    location = _decode_location(headers)
    max_age = _decode_max_age(headers)
    return Response(origin, st, location, max_age, seq, ping)


def _decode_notify(headers: dict[str, str], body: bytes) -> Alive | Update | Byebye:
    nts = _need(headers, "NTS")
    kind = _NTS_TYPE.get(nts)
    if kind is None:
        raise _Rejected("unsupported", f"NTS {nts[:80]!r}")
    origin = _decode_origin(headers, kind)
    nt = _need(headers, "NT")
    if nt != fleet_target(origin.fleet):
        raise _Rejected("bad-value", f"NT {nt[:80]!r} is not {fleet_target(origin.fleet)!r}")
    _check_usn(headers, origin)
    if kind == "byebye":
        return Byebye(origin)
    location = _decode_location(headers)
    max_age = _decode_max_age(headers)
    if kind == "alive":
        return Alive(origin, location, max_age)
    part, parts = _decode_part(_need(headers, "X-SDFR-PART"))
    base_text = headers.get("X-SDFR-BASE")
    if base_text is None:
        services, removed = _decode_services(headers, body, delta=False)
        return Update(origin, location, max_age, part, parts, services)
    base = _int_value("X-SDFR-BASE", base_text, 0, MAX_VERSION)
    if base >= origin.version or (part, parts) != (0, 1):
        raise _Rejected(
            "bad-value", f"X-SDFR-BASE {base} on part {part + 1}/{parts} of {origin.version}"
        )
    services, removed = _decode_services(headers, body, delta=True)
    return Update(origin, location, max_age, 0, 1, services, base, removed)


def _decode_origin(headers: dict[str, str], kind: str) -> Origin:
    try:
        given = headers["X-SDFR-TYPE"]
        fleet_text = headers["X-SDFR-FLEET"]
        robot_id = headers["X-SDFR-ROBOT"]
        version_text = headers["X-SDFR-VERSION"]
        digest = headers["X-SDFR-DIGEST"]
        boot_text = headers["BOOTID.UPNP.ORG"]
    except KeyError as missing:
        raise _Rejected("missing-header", str(missing.args[0])) from None
    if given != kind:
        raise _Rejected("bad-value", f"X-SDFR-TYPE {given[:40]!r} on a {kind} message")
    fleet = _int_value("X-SDFR-FLEET", fleet_text, 0, MAX_FLEET)
    if not ROBOT_ID_RE.fullmatch(robot_id):
        raise _Rejected("bad-value", f"X-SDFR-ROBOT {robot_id[:80]!r}")
    version = _int_value("X-SDFR-VERSION", version_text, 0, MAX_VERSION)
    if not _is_digest(digest):
        raise _Rejected("bad-value", f"X-SDFR-DIGEST {digest[:40]!r}")
    boot_id = _int_value("BOOTID.UPNP.ORG", boot_text, 0, MAX_BOOT_ID)
    config = headers.get("CONFIGID.UPNP.ORG")
    if config is not None and _parse_int(config, 0, CONFIGID_MODULUS - 1) != (
        version % CONFIGID_MODULUS
    ):
        raise _Rejected("bad-value", f"CONFIGID.UPNP.ORG {config[:40]!r} does not match version")
    return Origin(fleet, robot_id, boot_id, version, digest)


def _check_usn(headers: dict[str, str], origin: Origin) -> None:
    value = headers.get("USN")
    if value is None:
        return
    prefix = "uuid:" + origin.robot_id
    if not value.startswith(prefix) or (len(value) > len(prefix) and value[len(prefix)] != ":"):
        raise _Rejected("bad-value", f"USN {value[:80]!r} is not robot {origin.robot_id!r}")


def _decode_location(headers: dict[str, str]) -> str:
    location = _need(headers, "LOCATION")
    if not location or len(location) > MAX_LOCATION:
        raise _Rejected("bad-value", f"LOCATION must be 1..{MAX_LOCATION} characters")
    return location


def _decode_max_age(headers: dict[str, str]) -> int:
    value = _need(headers, "CACHE-CONTROL")
    if value.startswith("max-age="):
        got = _parse_int(value[8:], 1, MAX_MAX_AGE)
        if got is not None:
            return got
    for directive in value.split(","):
        name, eq, arg = directive.partition("=")
        if eq and name.strip().lower() == "max-age":
            got = _parse_int(arg.strip().strip('"'), 1, MAX_MAX_AGE)
            if got is not None:
                return got
            break
    raise _Rejected("bad-value", f"CACHE-CONTROL {value[:80]!r} has no max-age 1..{MAX_MAX_AGE}")


def _decode_part(value: str) -> tuple[int, int]:
    num, slash, total = value.partition("/")
    part = _parse_int(num.strip(), 1, MAX_PARTS)
    parts = _parse_int(total.strip(), 1, MAX_PARTS)
    if not slash or part is None or parts is None or part > parts:
        raise _Rejected("bad-value", f"X-SDFR-PART {value[:40]!r} is not i/n with 1 <= i <= n")
    return part - 1, parts


def _decode_services(
    headers: dict[str, str], body: bytes, *, delta: bool
) -> tuple[tuple[Service, ...], tuple[str, ...]]:
    length = headers.get("CONTENT-LENGTH")
    if length is not None:
        want = _int_value("CONTENT-LENGTH", length, 0, MAX_DATAGRAM)
        if len(body) != want:
            raise _Rejected("bad-body", f"body is {len(body)} bytes, CONTENT-LENGTH {want}")
    try:
        obj = _JSON_DECODER.decode(body.decode())
    except (ValueError, RecursionError) as exc:  # UnicodeDecodeError is a ValueError
        raise _Rejected("bad-body", f"not JSON: {exc}") from None
    if not isinstance(obj, dict):
        raise _Rejected("bad-body", "body must be a JSON object")
    items = obj.get("services")
    if not isinstance(items, list):
        raise _Rejected("bad-body", '"services" must be a list')
    services: list[Service] = []
    ids: set[str] = set()
    for i, item in enumerate(items):
        try:
            service = Service.from_json(item)
        except ValidationError as exc:
            raise _Rejected("bad-body", f"services[{i}]: {exc}") from None
        if service.id in ids:
            raise _Rejected("bad-body", f"services[{i}]: duplicate id {service.id!r}")
        ids.add(service.id)
        services.append(service)
    removed = obj.get("removed", [])
    if removed and not delta:
        raise _Rejected("bad-body", '"removed" only belongs to a delta (X-SDFR-BASE)')
    if not isinstance(removed, list) or not all(
        isinstance(r, str) and SERVICE_ID_RE.fullmatch(r) for r in removed
    ):
        raise _Rejected("bad-body", '"removed" must be a list of service ids')
    if len(set(removed)) != len(removed) or ids.intersection(removed):
        raise _Rejected("bad-body", '"removed" ids must be unique and not also added')
    return tuple(services), tuple(removed)


def _parse_want(value: str) -> Want:
    if value.lower() == WANT_ALL:
        return WANT_ALL
    indices: set[int] = set()
    for piece in value.split(","):
        index = _parse_int(piece.strip(), 0, MAX_PARTS)
        if index is None:
            raise _Rejected("bad-value", f"X-SDFR-WANT {value[:80]!r}")
        indices.add(index)
    return tuple(sorted(indices))


def _host_only(value: str) -> str:
    """The address part of a HOST value: `a.b.c.d:port`, `[v6]:port` or a bare address."""
    if value.startswith("["):
        close = value.find("]")
        return value[1:close] if close > 0 else value
    host, colon, _ = value.rpartition(":")
    return host if colon and ":" not in host else value


def _need(headers: dict[str, str], name: str) -> str:
    value = headers.get(name)
    if value is None:
        raise _Rejected("missing-header", name)
    return value


def _parse_int(text: str, lo: int, hi: int) -> int | None:
    """A plain decimal (ASCII digits only) in lo..hi, else None."""
    if not 0 < len(text) <= 20 or not text.isascii() or not text.isdigit():
        return None
    value = int(text)
    return value if lo <= value <= hi else None


def _int_value(name: str, text: str, lo: int, hi: int) -> int:
    value = _parse_int(text, lo, hi)
    if value is None:
        raise _Rejected("bad-value", f"{name} {text[:40]!r} is not an integer {lo}..{hi}")
    return value


def _optional_int(headers: dict[str, str], name: str, hi: int) -> int | None:
    text = headers.get(name)
    return None if text is None else _int_value(name, text, 0, hi)
