"""The messages a datagram carries, the format's limits, and what encoder and decoder share."""

import ipaddress
import json
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Literal, NoReturn, TypeAlias

from sdfr import __version__
from sdfr.records.model import Service, by_id

MAX_DATAGRAM = 1400
#: Room every encoded datagram leaves for a seal (sdfr.protocol.auth): a keyed fleet then has
#: exactly the limits of an open one, and a service accepted before a key was set still fits after.
SEAL_RESERVE = 80
#: Largest datagram `encode` and `encode_update_parts` produce.
MAX_ENCODED = MAX_DATAGRAM - SEAL_RESERVE
DEFAULT_GROUP = "239.255.255.250"
DEFAULT_PORT = 1900
DEVICE_TYPE = "urn:sdfr-org:device:robot:1"
SERVER = f"Linux UPnP/1.1 SDfR/{__version__}"

MAX_FLEET = 255
MAX_BOOT_ID = 2**31 - 1
MAX_VERSION = 2**53
#: Sequence numbers of pings and beacons are random 64-bit nonces (a reply proves freshness).
MAX_SEQ = 2**64 - 1
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
#: Wire versions: 1 speaks only the full SSDP-style forms; 2 also reads and writes the
#: compact forms (see `encode`), and says so on its full forms (X-SDFR-WIRE: 2).
WIRE_FULL = 1
WIRE_COMPACT = 2


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
    robot_id: str  # sdfr.records.model.ROBOT_ID_RE, X-SDFR-ROBOT
    boot_id: int  # BOOTID.UPNP.ORG, 0 .. 2**31-1
    version: int  # X-SDFR-VERSION, 0 .. 2**53; CONFIGID.UPNP.ORG carries version % 2**24
    digest: str  # X-SDFR-DIGEST, 16 lowercase hex chars (sdfr.records.model.service_digest)
    #: The wire version the sender speaks (X-SDFR-WIRE; WIRE_COMPACT for a compact datagram).
    wire: int = WIRE_FULL


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
    #: A fetch's X-SDFR-HAVE: the version of the robot's set the fetcher holds (same boot),
    #: so that the answer can be what changed since rather than the whole set.
    have: int | None = None


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
    #: A compact delta's body as it came, deflated against the base set (`services` and
    #: `removed` are then empty): only a robot holding that set can read it, with
    #: `sdfr.wire.unpack_delta`.  None for every other Update.
    packed: bytes | None = None
    #: A compact delta's earlier steps, oldest first: (base, body) each, the body as on the
    #: wire (deflated against that base set, or its JSON), each turning its base into the
    #: next step's base and the last into `base`.  A robot that missed the changes of the
    #: last deltas applies them from the set it holds, with `sdfr.wire.read_step`.
    steps: tuple[tuple[int, bytes], ...] = ()


@dataclass(frozen=True, slots=True)
class Alive:
    """`NOTIFY` with `NTS: ssdp:alive`: the beacon, no body.

    With `seq` it is also a ping to every robot that hears it (X-SDFR-SEQ), each answering
    with a ping reply of that sequence number; with `turns` above 1 (compact only), to those
    whose turn it is (`sdfr.protocol.answers_beacon`), so that a robot answers a bounded
    number of beacons however large the fleet.  A compact Alive may leave `location` empty
    (the robot's address did not change) and has no max-age (0)."""

    origin: Origin
    location: str
    max_age: int
    seq: int | None = None
    turns: int = 1


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
#: A compact Update's body that starts with this byte is raw deflate (RFC 1951) of the JSON
#: (which always starts with "{"); a delta's against `delta_dictionary` of its base set.
PACKED = b"Z"
#: Most turns a beacon's pinged robots may take (`Alive.turns`).
MAX_TURNS = 1024
#: Most steps one compact delta carries (its own and the earlier ones of `Update.steps`).
MAX_STEPS = 4
#: Most bytes a packed body may inflate to (a part's JSON is far smaller): no inflate bomb.
MAX_UNPACKED = 256 * 1024
#: Deflate's window: the most of a dictionary it can use.
_WINDOW = 32768


def _no_constant(name: str) -> NoReturn:
    raise ValueError(f"{name} is not JSON")


_JSON_DECODER = json.JSONDecoder(parse_constant=_no_constant)


@lru_cache(maxsize=256)
def _is_multicast(host: str) -> bool:
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    try:
        return ipaddress.ip_address(host).is_multicast
    except ValueError:
        return False


def delta_dictionary(services: Sequence[Service]) -> bytes:
    """What a packed delta is deflated against: its base set's services as JSON, by id.  The
    sender and a robot holding the base set make the same bytes (the digest vouches for the
    set): a new service much like the others then takes a few dozen bytes."""
    return b",".join(s.json_text() for s in sorted(services, key=by_id))[-_WINDOW:]


def _is_digest(value: str) -> bool:
    return isinstance(value, str) and len(value) == 16 and not value.strip(_HEX)
