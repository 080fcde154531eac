"""Encoding: a message to the bytes of one datagram (the full form here, the compact one in
`compact`); what fits in an Update."""

from collections.abc import Sequence
from functools import cache, lru_cache

from sdfr.errors import ValidationError
from sdfr.records.model import Service
from sdfr.wire.compact import _compact, _compact_parts
from sdfr.wire.fields import (
    _body,
    _check_location,
    _check_max_age,
    _check_origin,
    _check_range,
    _check_text,
    _check_unique_ids,
    _check_update_shape,
    _delta_body,
    _finish,
    _host,
    _service_json,
    _want_text,
)
from sdfr.wire.messages import (
    _BODY_WRAP,
    _MAN,
    _MSEARCH_LINE,
    _NOTIFY_LINE,
    _OK_LINE,
    CONFIGID_MODULUS,
    DEFAULT_GROUP,
    DEFAULT_PORT,
    MAX_BOOT_ID,
    MAX_ENCODED,
    MAX_FLEET,
    MAX_HOST,
    MAX_LOCATION,
    MAX_MAX_AGE,
    MAX_MX,
    MAX_PARTS,
    MAX_SEQ,
    MAX_VERSION,
    SERVER,
    WIRE_COMPACT,
    WIRE_FULL,
    Alive,
    Byebye,
    Discovery,
    Message,
    Origin,
    Response,
    Update,
    _is_multicast,
    fleet_target,
    usn,
)


def encode(
    msg: Message,
    *,
    group: str = DEFAULT_GROUP,
    port: int = DEFAULT_PORT,
    compact: bool = False,
    dictionary: bytes | None = None,
) -> bytes:
    """The datagram for `msg`; ValueError if a field is out of range or it exceeds MAX_ENCODED.

    `group` and `port` fill the HOST header of M-SEARCH and NOTIFY (for a unicast search pass the
    peer's address and `multicast=False`).

    `compact`: the form only SDfR robots of wire version 2 read (`decode` reads both).  The
    origin's seven header lines become one (``X-SDFR: <type> <fleet> <robot> <boot> <version>
    <digest> [<field>]``, the field a ping's or beacon's sequence number (a beacon's with
    ``/<turns>``), a ping reply's, or a delta's base; a fetch's three lines become
    ``X-SDFR-WANT: <parts> <version> [<have>]``) and the lines only a UPnP control point
    needs go (HOST, MAN, NT, NTS, USN, SERVER, CACHE-CONTROL, CONFIGID, CONTENT-TYPE,
    CONTENT-LENGTH; LOCATION unless given): a beacon takes about 75 bytes instead of 430.
    Searches only by unicast (pings, fetches), responses only as ping replies; plain SSDP
    clients always get the full form.  A compact delta's body is deflated against
    `dictionary` (`delta_dictionary` of its base set) when given and that is shorter; a
    delta may carry earlier steps (`Update.steps`: its base field is then
    ``<base>/<length>,...,<base>`` and its body their bodies, then its own).
    """
    if compact:
        return _compact(msg, dictionary)
    if isinstance(msg, Update):
        _check_update_shape(msg.part, msg.parts)
        blobs = [_service_json(s) for s in msg.services]
        _check_unique_ids(msg.services)
        prefix = _update_prefix(msg.origin, msg.location, msg.max_age, _host(group, port))
        if msg.steps:
            raise ValueError("a delta's earlier steps go only in the compact form")
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
        if msg.turns != 1:
            raise ValueError("a beacon's turns go only in the compact form")
        _check_location(msg.location)
        _check_max_age(msg.max_age)
        lines = _notify_lines(msg.origin, "alive", _host(group, port))
        lines.insert(2, f"LOCATION: {msg.location}")
        lines.insert(2, f"CACHE-CONTROL: max-age={msg.max_age}")
        if msg.seq is not None:
            _check_range("seq", msg.seq, 0, MAX_SEQ)
            lines.append(f"X-SDFR-SEQ: {msg.seq}")
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
    compact: bool = False,
) -> list[bytes]:
    """Split a whole service set into as few Update datagrams as greedy packing allows.

    Parts are numbered 0..n-1 with the same total, each at most MAX_ENCODED bytes, and keep the
    order of `services`; an empty set is one part with no services.  ValueError when a single
    service cannot fit in a datagram alone, ids repeat, or the set needs more than 255 parts.
    `compact`: the compact form (see `encode`), LOCATION kept.
    """
    if compact:
        return _compact_parts(origin, location, services)
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
    origin = Origin(MAX_FLEET, robot_id, MAX_BOOT_ID, 2**53 - 1, "f" * 16, WIRE_COMPACT)
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


def _origin_lines(origin: Origin, kind: str) -> list[str]:
    _check_origin(origin)
    lines = [
        f"BOOTID.UPNP.ORG: {origin.boot_id}",
        f"CONFIGID.UPNP.ORG: {origin.version % CONFIGID_MODULUS}",
        f"X-SDFR-FLEET: {origin.fleet}",
        f"X-SDFR-ROBOT: {origin.robot_id}",
        f"X-SDFR-TYPE: {kind}",
        f"X-SDFR-VERSION: {origin.version}",
        f"X-SDFR-DIGEST: {origin.digest}",
    ]
    if origin.wire != WIRE_FULL:
        lines.append(f"X-SDFR-WIRE: {origin.wire}")
    return lines


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
        if (msg.seq, msg.want, msg.want_version, msg.have) != (None, None, None, None):
            raise ValueError("seq, want, want_version and have need an origin (X-SDFR-*)")
        return lines
    lines += _origin_lines(msg.origin, "discovery")
    return lines + _search_lines(msg)


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


def _search_lines(msg: Discovery) -> list[str]:
    """A full-form search's SDfR lines beyond its origin: the ping's sequence number, what a
    fetch wants, and the set its sender holds (the compact form: `_compact_fetch`)."""
    lines = []
    if msg.seq is not None:
        _check_range("seq", msg.seq, 0, MAX_SEQ)
        lines.append(f"X-SDFR-SEQ: {msg.seq}")
    if msg.want is not None:
        lines.append(f"X-SDFR-WANT: {_want_text(msg.want)}")
    if msg.want_version is not None:
        _check_range("want_version", msg.want_version, 0, MAX_VERSION)
        lines.append(f"X-SDFR-WANT-VERSION: {msg.want_version}")
    if msg.have is not None:
        _check_range("have", msg.have, 0, MAX_VERSION)
        lines.append(f"X-SDFR-HAVE: {msg.have}")
    return lines
