"""Decoding: the bytes of one datagram to a message, or a `Reject` saying why not.  Never
raises: a bad datagram is a value."""

import re
import zlib
from collections.abc import Sequence
from itertools import pairwise

from sdfr.errors import ValidationError
from sdfr.records.model import ROBOT_ID_RE, SERVICE_ID_RE, Service
from sdfr.wire.messages import (
    _JSON_DECODER,
    _MAN,
    _MSEARCH_LINE,
    _NOTIFY_LINE,
    _NTS_TYPE,
    CONFIGID_MODULUS,
    MAX_BOOT_ID,
    MAX_DATAGRAM,
    MAX_FLEET,
    MAX_LOCATION,
    MAX_MAX_AGE,
    MAX_MX,
    MAX_MX_ACCEPTED,
    MAX_PARTS,
    MAX_SEQ,
    MAX_STEPS,
    MAX_TURNS,
    MAX_UNPACKED,
    MAX_VERSION,
    PACKED,
    WANT_ALL,
    WIRE_COMPACT,
    WIRE_FULL,
    Alive,
    Byebye,
    Discovery,
    Message,
    Origin,
    Reject,
    Response,
    Update,
    Want,
    _is_digest,
    _is_multicast,
    delta_dictionary,
    fleet_target,
)


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


#: Control characters (C0 but HTAB, DEL, C1) and Unicode's line and paragraph separators.
_CONTROL = re.compile("[\x00-\x08\x0a-\x1f\x7f-\x9f\u2028\u2029]")
_FLEET_NEEDLE = b"\nX-SDFR-FLEET:"
_COMPACT_NEEDLE = b"\nX-SDFR: "
_COMPACT_METHOD = {"discovery": "M-SEARCH", "response": "200", "alive": "NOTIFY",
                   "update": "NOTIFY", "byebye": "NOTIFY"}  # fmt: skip


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
        at = data.find(_COMPACT_NEEDLE, 0, end)
        if at >= 0:  # X-SDFR: <type> <fleet> ...
            words = data[at + len(_COMPACT_NEEDLE) : at + len(_COMPACT_NEEDLE) + 20].split(b" ")
            raw = words[1] if len(words) > 2 else b""
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
        line = lines[i]
        if line[-1:] == "\r":
            line = line[:-1]
        if _CONTROL.search(line):
            # (HTTP's rule: no control character in a field but HTAB.  Text from here reaches
            # the history map, the API and logs: no forged lines, no terminal escapes.)
            raise _Rejected("bad-value", f"control character in {line[:80]!r}")
        name, colon, value = line.partition(":")
        key = name.strip().upper()
        if not colon or not key or " " in key or "\t" in key:
            raise _Rejected("bad-header", f"not a header line: {lines[i][:80]!r}")
        value = value.strip(" \t")
        if setdefault(key, value) != value:
            raise _Rejected("bad-header", f"{key} given twice with different values")
    if "X-SDFR" in headers:
        return _decode_compact(method, headers, data[body_start:], fleet)
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
    have = _optional_int(headers, "X-SDFR-HAVE", MAX_VERSION)
    return Discovery(origin, st, mx, seq, want, want_version, multicast, have)


def _decode_compact(
    method: str, headers: dict[str, str], body: bytes, fleet: int | None
) -> Message | Reject:
    """A compact datagram (see `sdfr.wire.encode`): the origin in one X-SDFR line."""
    words = headers["X-SDFR"].split(" ")
    if len(words) not in (6, 7):
        raise _Rejected("bad-value", f"X-SDFR {headers['X-SDFR'][:80]!r}: not 6 or 7 fields")
    kind, fleet_text, robot_id, boot_text, version_text, digest = words[:6]
    extra = words[6] if len(words) == 7 else None
    got = _int_value("X-SDFR fleet", fleet_text, 0, MAX_FLEET)
    if fleet is not None and got != fleet:
        return Reject("other-fleet", f"fleet {got}, not {fleet}")
    if _COMPACT_METHOD.get(kind) != method:
        raise _Rejected("bad-value", f"X-SDFR type {kind[:40]!r} on a {method} datagram")
    if not ROBOT_ID_RE.fullmatch(robot_id):
        raise _Rejected("bad-value", f"X-SDFR robot {robot_id[:80]!r}")
    if not _is_digest(digest):
        raise _Rejected("bad-value", f"X-SDFR digest {digest[:40]!r}")
    origin = Origin(
        got,
        robot_id,
        _int_value("X-SDFR boot", boot_text, 0, MAX_BOOT_ID),
        _int_value("X-SDFR version", version_text, 0, MAX_VERSION),
        digest,
        WIRE_COMPACT,
    )
    if kind == "update" and extra is not None:
        return _decode_compact_delta(origin, headers, body, extra)
    if kind == "byebye" and extra is not None:
        raise _Rejected("bad-value", "X-SDFR byebye with a seventh field")
    turns = 1
    if kind == "alive" and extra is not None and "/" in extra:
        extra, _, turns_text = extra.partition("/")
        turns = _int_value("X-SDFR turns", turns_text, 2, MAX_TURNS)
    seq = None if extra is None else _int_value("X-SDFR seq", extra, 0, MAX_SEQ)
    if kind == "discovery":
        st = _need(headers, "ST")
        if not st:
            raise _Rejected("bad-value", "ST is empty")
        want, want_version, have = _compact_want(headers.get("X-SDFR-WANT"))
        return Discovery(origin, st, 0, seq, want, want_version, False, have)
    if kind == "response":
        if seq is None:
            raise _Rejected("bad-value", "X-SDFR response without a seq (it is a ping reply)")
        st = headers.get("ST") or f"uuid:{robot_id}"
        return Response(origin, st, "", 0, seq, _optional_int(headers, "X-SDFR-PING", MAX_SEQ))
    if kind == "byebye":
        return Byebye(origin)
    location = _compact_location(headers)
    if kind == "alive":
        return Alive(origin, location, 0, seq, turns)
    part_text = headers.get("X-SDFR-PART")
    if part_text is None:
        raise _Rejected("bad-value", "a compact update has X-SDFR-PART or a base, one")
    part, parts = _decode_part(part_text)
    if body.startswith(PACKED):
        body = _inflate(body[len(PACKED) :], None)
    services, _ = _decode_services(headers, body, delta=False)
    return Update(origin, location, 0, part, parts, services)


def _compact_location(headers: dict[str, str]) -> str:
    location = headers.get("LOCATION", "")
    if len(location) > MAX_LOCATION or ("LOCATION" in headers and not location) or "\t" in location:
        raise _Rejected("bad-value", f"LOCATION must be 1..{MAX_LOCATION} characters")
    return location


def _compact_want(text: str | None) -> tuple[Want, int | None, int | None]:
    """A compact fetch's ``X-SDFR-WANT: <parts> [<version> [<have>]]`` ("-": none)."""
    if text is None:
        return None, None, None
    words = text.split(" ")
    if not 1 <= len(words) <= 3 or words[-1] == "-":
        raise _Rejected("bad-value", f"X-SDFR-WANT {text[:80]!r}: not <parts> [<version> [<have>]]")
    words += ["-"] * (3 - len(words))
    want = None if words[0] == "-" else _parse_want(words[0])
    version = (
        None if words[1] == "-" else _int_value("X-SDFR-WANT version", words[1], 0, MAX_VERSION)
    )
    have = None if words[2] == "-" else _int_value("X-SDFR-WANT have", words[2], 0, MAX_VERSION)
    return want, version, have


def _decode_compact_delta(
    origin: Origin, headers: dict[str, str], body: bytes, chain: str
) -> Update:
    """A compact delta: its bases ``<base>/<length>,...,<base>`` and body (earlier steps'
    bodies, then its own)."""
    if "X-SDFR-PART" in headers:
        raise _Rejected("bad-value", "a compact update has X-SDFR-PART or a base, one")
    location = _compact_location(headers)
    fields = chain.split(",")
    if len(fields) > MAX_STEPS:
        raise _Rejected("bad-value", f"a delta of {len(fields)} steps, more than {MAX_STEPS}")
    steps: list[tuple[int, bytes]] = []
    at = 0
    for field in fields[:-1]:
        base_text, slash, length_text = field.partition("/")
        if not slash:
            raise _Rejected("bad-value", f"delta step {field[:40]!r}: not <base>/<length>")
        base = _int_value("delta step base", base_text, 0, MAX_VERSION)
        length = _int_value("delta step length", length_text, 1, len(body) - at)
        steps.append((base, body[at : at + length]))
        at += length
    base = _int_value("delta base", fields[-1], 0, MAX_VERSION)
    bases = [b for b, _ in steps] + [base, origin.version]
    if any(b >= nxt for b, nxt in pairwise(bases)):
        raise _Rejected("bad-value", f"delta bases {bases[:-1]!r} on version {origin.version}")
    own = body[at:]
    if own.startswith(PACKED):  # only a robot holding the base set can read it
        return Update(origin, location, 0, 0, 1, (), base, (), own[len(PACKED) :], tuple(steps))
    services, removed = _decode_services(headers, own, delta=True, compact=True)
    return Update(origin, location, 0, 0, 1, services, base, removed, None, tuple(steps))


def _inflate(data: bytes, dictionary: bytes | None) -> bytes:
    """A packed body's JSON; never more than MAX_UNPACKED bytes of it."""
    try:
        d = zlib.decompressobj(-15, zdict=dictionary) if dictionary else zlib.decompressobj(-15)
        out = d.decompress(data, MAX_UNPACKED + 1)
        if len(out) > MAX_UNPACKED:
            raise _Rejected("bad-body", f"inflates to more than {MAX_UNPACKED} bytes")
        if not d.eof or d.unused_data:
            raise _Rejected("bad-body", "the deflated body is cut short or has trailing bytes")
    except zlib.error as exc:
        raise _Rejected("bad-body", f"not a deflated body: {exc}") from None
    return out


def unpack_delta(
    msg: Update, base: Sequence[Service], dictionary: bytes | None = None
) -> Update | Reject:
    """A packed delta (`Update.packed`) read against its base set `base` (the services of
    version `msg.base` the reader holds): the same Update with its services and removed ids;
    a Reject when it does not inflate or parse (the reader's set was not the base after all:
    the digest check that follows catches the rest).  An unpacked Update comes back as is.
    `dictionary`: `delta_dictionary(base)` when the caller has it already."""
    if msg.packed is None:
        return msg
    read = read_step(PACKED + msg.packed, base, dictionary)
    if isinstance(read, Reject):
        return read
    services, removed = read
    return Update(
        msg.origin, msg.location, msg.max_age, 0, 1, services, msg.base, removed, None, msg.steps
    )


def read_step(
    body: bytes, base: Sequence[Service], dictionary: bytes | None = None
) -> tuple[tuple[Service, ...], tuple[str, ...]] | Reject:
    """One step of a compact delta (`Update.steps`) read against its base set `base`: the
    services it adds or replaces and the ids it removes; a Reject when it does not inflate or
    parse.  `dictionary`: `delta_dictionary(base)` when the caller has it already."""
    try:
        if body.startswith(PACKED):
            body = _inflate(body[len(PACKED) :], dictionary or delta_dictionary(base))
        return _decode_services({}, body, delta=True, compact=True)
    except _Rejected as rej:
        return Reject(rej.reason, rej.detail)


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
        return Alive(origin, location, max_age, _optional_int(headers, "X-SDFR-SEQ", MAX_SEQ))
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
    wire_text = headers.get("X-SDFR-WIRE")
    wire = WIRE_FULL if wire_text is None else _int_value("X-SDFR-WIRE", wire_text, 1, 9)
    return Origin(fleet, robot_id, boot_id, version, digest, wire)


def _check_usn(headers: dict[str, str], origin: Origin) -> None:
    value = headers.get("USN")
    if value is None:
        return
    prefix = "uuid:" + origin.robot_id
    if not value.startswith(prefix) or (len(value) > len(prefix) and value[len(prefix)] != ":"):
        raise _Rejected("bad-value", f"USN {value[:80]!r} is not robot {origin.robot_id!r}")


def _decode_location(headers: dict[str, str]) -> str:
    location = _need(headers, "LOCATION")
    if not location or len(location) > MAX_LOCATION or "\t" in location:
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
    headers: dict[str, str], body: bytes, *, delta: bool, compact: bool = False
) -> tuple[tuple[Service, ...], tuple[str, ...]]:
    """The services (and a delta's removed ids) of an Update's body; a compact delta may
    leave out an empty list."""
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
    items = obj.get("services", [] if compact else None)
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
