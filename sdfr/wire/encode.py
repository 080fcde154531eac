"""Encoding: a message to the bytes of one datagram; what fits in an Update."""

import zlib
from collections import Counter
from collections.abc import Sequence
from functools import cache, lru_cache
from itertools import pairwise
from typing import Literal

from sdfr.errors import ValidationError
from sdfr.model import ROBOT_ID_RE, SERVICE_ID_RE, Service
from sdfr.wire.messages import (
    _BODY_CLOSE,
    _BODY_OPEN,
    _BODY_WRAP,
    _JSON_ENCODER,
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
    MAX_STEPS,
    MAX_TURNS,
    MAX_VERSION,
    PACKED,
    SERVER,
    WANT_ALL,
    WIRE_COMPACT,
    WIRE_FULL,
    Alive,
    Byebye,
    Discovery,
    Message,
    Origin,
    Response,
    Update,
    _is_digest,
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


def _deflater(dictionary: bytes | None = None) -> "zlib._Compress":
    level = 6  # nearly 9's ratio on such JSON, at a fraction of its time
    if dictionary:
        return zlib.compressobj(level, zlib.DEFLATED, -15, 9, zlib.Z_DEFAULT_STRATEGY, dictionary)
    return zlib.compressobj(level, zlib.DEFLATED, -15, 9)


def _pack_body(body: bytes, dictionary: bytes | None = None) -> bytes:
    """`body` deflated (with its marker) when that is shorter, else as it is."""
    c = _deflater(dictionary)
    packed = PACKED + c.compress(body) + c.flush()
    return packed if len(packed) < len(body) else body


def _compact_parts(origin: Origin, location: str, services: Sequence[Service]) -> list[bytes]:
    """A whole set in compact parts: each part's JSON deflated, as many services a part as
    fit once deflated (a set of similar services takes a fifth of the datagrams)."""
    _check_location(location)
    _check_unique_ids(services)
    prefix = _compact_head(origin, "update") + f"LOCATION: {location}\r\n".encode()
    blobs = [_service_json(s) for s in services]
    # The most a body may take, with the longest part line this set could need.
    room = MAX_ENCODED - len(prefix) - len(f"X-SDFR-PART: {MAX_PARTS}/{MAX_PARTS}\r\n\r\n")
    bodies: list[bytes] = []
    group: list[bytes] = []
    c = _deflater()
    done = c.compress(_BODY_OPEN)

    def close() -> None:
        # The part as measured: deflated, or its plain JSON when that is no longer.
        packed = PACKED + done + c.compress(_BODY_CLOSE) + c.flush()
        plain = _body(group)
        bodies.append(packed if len(packed) < len(plain) else plain)

    raw = _BODY_WRAP
    for blob in blobs:
        piece = (b"," if group else b"") + blob
        raw += len(piece)
        if raw > room - 8 and group:  # deflated it may still fit: measure (a flush of a copy)
            trial = c.copy()
            size = len(PACKED) + len(done) + len(trial.compress(piece + _BODY_CLOSE))
            if size + len(trial.flush()) > room:  # full: the next part starts here
                close()
                group, c = [], _deflater()
                done = c.compress(_BODY_OPEN)
                piece, raw = blob, _BODY_WRAP + len(blob)
        group.append(blob)
        done += c.compress(piece)
    close()
    if len(bodies) > MAX_PARTS:
        raise ValueError(
            f"{len(services)} services need {len(bodies)} update parts, more than {MAX_PARTS}"
        )
    out = []
    for i, body in enumerate(bodies):
        part = f"X-SDFR-PART: {i + 1}/{len(bodies)}\r\n\r\n".encode()
        out.append(_finish(prefix + part, body, "Update"))
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
    removed = _JSON_ENCODER.encode(list(msg.removed)).encode()
    if compact and not msg.services:
        return b'{"removed":' + removed + b"}"
    full = _body([_service_json(s) for s in msg.services])
    if compact and not msg.removed:
        return full
    return full[:-1] + b',"removed":' + removed + b"}"


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


_KIND = {Discovery: "discovery", Response: "response", Update: "update", Alive: "alive",
         Byebye: "byebye"}  # fmt: skip


def _compact_head(
    origin: Origin, kind: str, start: str = _NOTIFY_LINE, extra: str | None = None
) -> bytes:
    """The start line and the origin's one line of a compact datagram, with the type's one
    optional field last (a ping's sequence number, a delta's base)."""
    _check_origin(origin)
    if origin.wire < WIRE_COMPACT:
        raise ValueError(f"a compact datagram comes from wire {WIRE_COMPACT}, not {origin.wire}")
    tail = "" if extra is None else f" {extra}"
    return (
        f"{start}\r\nX-SDFR: {kind} {origin.fleet} {origin.robot_id} {origin.boot_id} "
        f"{origin.version} {origin.digest}{tail}\r\n"
    ).encode()


def _seq_text(seq: int | None) -> str | None:
    if seq is None:
        return None
    _check_range("seq", seq, 0, MAX_SEQ)
    return str(seq)


def _compact_fetch(msg: Discovery) -> list[str]:
    """A compact search's fetch, in one line: ``X-SDFR-WANT: <parts> [<version> [<have>]]``
    ("-" for one it has not; none of them: no line)."""
    if msg.want_version is not None:
        _check_range("want_version", msg.want_version, 0, MAX_VERSION)
    if msg.have is not None:
        _check_range("have", msg.have, 0, MAX_VERSION)
    words = [
        "-" if msg.want is None else _want_text(msg.want),
        "-" if msg.want_version is None else str(msg.want_version),
        "-" if msg.have is None else str(msg.have),
    ]
    while words and words[-1] == "-":
        words.pop()
    return [f"X-SDFR-WANT: {' '.join(words)}"] if words else []


def _delta_step(msg: Update, dictionary: bytes | None = None) -> bytes:
    """A compact delta's own step as it goes on the wire: its body, deflated against
    `dictionary` (`delta_dictionary` of its base set) when that is shorter."""
    body = _delta_body(msg, compact=True)
    return _pack_body(body, dictionary) if dictionary is not None else body


def last_step(data: bytes) -> bytes:
    """The body of a compact delta's own (last) step, out of the datagram `encode` made: what
    the next delta may carry as an earlier step (`Update.steps`)."""
    end = data.index(b"\r\n\r\n")
    line = data.index(b"\r\nX-SDFR: ") + 2
    field = data[line : data.index(b"\r\n", line)].rsplit(b" ", 1)[1]
    skip = sum(int(step.split(b"/")[1]) for step in field.split(b",")[:-1])
    return data[end + 4 + skip :]


def _chain(msg: Update, base: int) -> str:
    """A delta's bases on the X-SDFR line: ``<base>/<length>,`` per earlier step, then its own
    (`base`)."""
    if len(msg.steps) >= MAX_STEPS:
        raise ValueError(f"a delta carries at most {MAX_STEPS} steps, not {len(msg.steps) + 1}")
    bases = [b for b, _ in msg.steps] + [base]
    if any(not 0 <= b < nxt for b, nxt in pairwise(bases)):
        raise ValueError(f"a delta's steps must go from lower to higher bases: {bases!r}")
    if any(not body for _, body in msg.steps):
        raise ValueError("a delta's earlier step has an empty body")
    return "".join(f"{b}/{len(body)}," for b, body in msg.steps) + str(base)


def _compact(msg: Message, dictionary: bytes | None = None) -> bytes:
    """The compact form of `msg` (see `encode`)."""
    if msg.origin is None:
        raise ValueError("a plain SSDP search has no compact form")
    kind = _KIND[type(msg)]
    lines: list[str] = []
    body = b""
    extra = None
    if isinstance(msg, Discovery):
        start = _MSEARCH_LINE
        if msg.multicast or msg.mx:
            raise ValueError("a compact search is a unicast one, with MX 0")
        _check_text("ST", msg.st)
        lines.append(f"ST: {msg.st}")
        extra = _seq_text(msg.seq)
        lines += _compact_fetch(msg)
    elif isinstance(msg, Response):
        start = _OK_LINE
        if msg.seq is None or msg.location or msg.max_age:
            raise ValueError("a compact response is a ping reply: seq, no location, max_age 0")
        _check_text("ST", msg.st)
        if msg.st != f"uuid:{msg.origin.robot_id}":
            lines.append(f"ST: {msg.st}")
        extra = _seq_text(msg.seq)
        if msg.ping is not None:
            _check_range("ping", msg.ping, 0, MAX_SEQ)
            lines.append(f"X-SDFR-PING: {msg.ping}")
    else:
        start = _NOTIFY_LINE
        if isinstance(msg, Alive | Update) and msg.location:
            _check_location(msg.location)
            lines.append(f"LOCATION: {msg.location}")
        if isinstance(msg, Alive):
            extra = _seq_text(msg.seq)
            if msg.turns != 1:
                _check_range("turns", msg.turns, 2, MAX_TURNS)
                if extra is None:
                    raise ValueError("a beacon's turns go with its seq")
                extra += f"/{msg.turns}"
        if isinstance(msg, Update):
            _check_update_shape(msg.part, msg.parts)
            _check_unique_ids(msg.services)
            if msg.base is not None:
                extra = _chain(msg, msg.base)
                body = b"".join(step for _, step in msg.steps) + _delta_step(msg, dictionary)
            else:
                if msg.removed or msg.steps:
                    raise ValueError("removed ids and steps belong to a delta Update (a base)")
                body = _body([_service_json(s) for s in msg.services])
                lines.append(f"X-SDFR-PART: {msg.part + 1}/{msg.parts}")
    head = _compact_head(msg.origin, kind, start, extra)
    tail = "".join(f"{line}\r\n" for line in lines) + "\r\n"
    return _finish(head + tail.encode(), body, type(msg).__name__)


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
