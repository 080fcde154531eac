"""Encoding in the compact form, the one SDfR robots of wire version 2 read (see `encode`)."""

import zlib
from collections.abc import Sequence
from itertools import pairwise

from sdfr.records.model import Service
from sdfr.wire.fields import (
    _body,
    _check_location,
    _check_origin,
    _check_range,
    _check_text,
    _check_unique_ids,
    _check_update_shape,
    _delta_body,
    _finish,
    _service_json,
    _want_text,
)
from sdfr.wire.messages import (
    _BODY_CLOSE,
    _BODY_OPEN,
    _BODY_WRAP,
    _MSEARCH_LINE,
    _NOTIFY_LINE,
    _OK_LINE,
    MAX_ENCODED,
    MAX_PARTS,
    MAX_SEQ,
    MAX_STEPS,
    MAX_TURNS,
    MAX_VERSION,
    PACKED,
    WIRE_COMPACT,
    Alive,
    Byebye,
    Discovery,
    Message,
    Origin,
    Response,
    Update,
)


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
