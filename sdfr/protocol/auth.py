"""Authenticated datagrams: the fleet keyring, seals and replay windows. No I/O, no clock.

A sealed datagram is an ordinary SDfR datagram with one more header line, always the last one
before the blank line::

    X-SDFR-AUTH: <key id> <counter> <to>:<from> <mac>

- key id: 8 lowercase hex characters naming the key (`key_id`), so a receiver holding several
  keys (a rotation in progress) knows which one to check with;
- counter: the sender's datagram counter, 1, 2, 3, ... within one boot of the sender.  The pair
  (boot id, counter) never repeats while the state directory lasts (see `sdfr.store`), so
  replays of a peer whose counter this robot has synchronised are recognised with a window per
  sender (`ReplayWindow`), as in RFC 7474;
- to: whom the datagram is for: ``*`` for the fleet (multicast), else 4 hex characters of a hash
  of the recipient's robot id; from: 4 hex characters of a hash of the sender's own IP address.
  Both are hints (a receiver drops a datagram for another robot, or one arriving from another
  address than its sender's, before computing any MAC); the MAC covers the recipient's whole
  robot id and the sender's whole address, so a datagram is bound to both: a relay cannot
  move a robot, and a unicast captured between two robots is worth nothing to a third;
- mac: HMAC-SHA256 under the key, truncated to 128 bits, base64url without padding (22
  characters), over a label, the recipient, the sender's address and the whole datagram with
  only the mac and its line end left out: every header, the boot id, the counter and the body.

The seal costs at most `wire.SEAL_RESERVE` bytes; the codec keeps that much room free in every
datagram, so a keyed fleet has exactly the limits of an open one.  Without a key nothing is
added and the wire is plain SSDP as before.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import zlib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Literal, TypeAlias, get_args

from sdfr.wire import MAX_DATAGRAM, SEAL_RESERVE, Reject

__all__ = [
    "AUTH_HEADER",
    "KEY_BYTES",
    "MODES",
    "OPEN",
    "REJECT_REASONS",
    "Keyring",
    "Mode",
    "ReplayWindow",
    "Sealed",
    "check",
    "key_id",
    "seal",
    "seal_of",
]

#: Length of a fleet key in bytes (256 bits).
KEY_BYTES = 32
KID_CHARS = 8
MAC_BYTES = 16
MAC_CHARS = 22  # base64url of 16 bytes, without the padding
MAX_COUNTER = 2**53
AUTH_HEADER = b"X-SDFR-AUTH: "
#: Domain separation: a key used for anything else never yields a valid SDfR seal.
_LABEL = b"SDfR-auth-v2\0"
_KID_LABEL = b"SDfR-key-id\0"
_HEX = frozenset(b"0123456789abcdef")
_B64URL = frozenset(b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_")

#: Whom a datagram for the whole fleet (multicast) is for.
FLEET = "*"
TAG_CHARS = 4
ROUTE_MAX = TAG_CHARS + 1 + TAG_CHARS
#: Longest seal line, "\r\n" included: it must fit the room the codec leaves.
SEAL_LINE_MAX = (
    len(AUTH_HEADER) + KID_CHARS + 1 + len(str(MAX_COUNTER)) + 1 + ROUTE_MAX + 1 + MAC_CHARS + 2
)
assert SEAL_LINE_MAX <= SEAL_RESERVE, (SEAL_LINE_MAX, SEAL_RESERVE)

#: How a robot with keys treats the fleet (without keys the fleet is open, whatever the mode):
#: - accept: sends unsigned, accepts signed and unsigned (step 1 of moving an open fleet to a
#:   key: every robot gets the key before any robot signs);
#: - sign: sends signed, still accepts unsigned (step 2: robots switch one by one);
#: - enforce: sends signed, accepts only signed datagrams (step 3, and the default).
Mode: TypeAlias = Literal["accept", "sign", "enforce"]
MODES: tuple[Mode, ...] = get_args(Mode)

#: Reasons `check` rejects a datagram for (counted like the codec's).
REJECT_REASONS = ("unsigned", "unknown-key", "bad-mac", "bad-seal", "not-for-me", "relayed")


@lru_cache(maxsize=64)
def key_id(key: bytes) -> str:
    """The public name of a key: 8 hex characters of a hash of it (not a secret)."""
    return hashlib.sha256(_KID_LABEL + key).hexdigest()[:KID_CHARS]


@dataclass(frozen=True, slots=True)
class Keyring:
    """The keys a robot accepts, the one it sends with, and the mode.

    `keys` maps key id to key.  No keys: an open fleet (nothing signed, nothing checked).
    """

    keys: Mapping[str, bytes] = field(default_factory=dict)
    primary: str | None = None
    mode: Mode = "enforce"

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, not {self.mode!r}")
        for kid, key in self.keys.items():
            if len(key) != KEY_BYTES:
                raise ValueError(f"key {kid} is {len(key)} bytes, not {KEY_BYTES}")
            if key_id(key) != kid:
                raise ValueError(f"key id {kid!r} does not name its key ({key_id(key)})")
        if self.keys and self.primary not in self.keys:
            raise ValueError(f"the primary key {self.primary!r} is not in the keyring")
        if not self.keys and self.primary is not None:
            raise ValueError("a primary key without keys")

    @classmethod
    def of(
        cls, keys: Iterable[bytes], primary: bytes | None = None, mode: Mode = "enforce"
    ) -> Keyring:
        """A keyring of raw keys; the primary defaults to the first."""
        ring = {key_id(k): k for k in keys}
        if primary is not None:
            ring.setdefault(key_id(primary), primary)
        first = primary if primary is not None else next(iter(ring.values()), None)
        return cls(ring, None if first is None else key_id(first), mode)

    @property
    def keyed(self) -> bool:
        return bool(self.keys)

    @property
    def signs(self) -> bool:
        """Whether datagrams go out sealed (with the primary key)."""
        return self.keyed and self.mode != "accept"

    @property
    def accepts_unsigned(self) -> bool:
        return not self.keyed or self.mode != "enforce"


#: No keys: the open fleet.
OPEN = Keyring()


def plain_ssdp_answered(wanted: bool | None, keyring: Keyring) -> bool:
    """Whether plain SSDP clients get the read-only ssdp:all answer: as configured
    (`ssdp_interop` on/off), or, when it is auto (None), only while the fleet has no key."""
    return not keyring.keyed if wanted is None else wanted


@dataclass(frozen=True, slots=True)
class Sealed:
    """A datagram whose seal checked out: the key it was sealed with, its counter, and whether
    it was for the whole fleet (multicast) rather than for this robot alone."""

    kid: str
    counter: int
    fleet: bool = True


def host_of(address: str) -> str:
    """An IP address as both ends of a seal write it: no brackets, no zone, lower case."""
    return address.strip("[]").partition("%")[0].lower()


@lru_cache(maxsize=1024)
def _tag(text: str) -> bytes:
    return b"%04x" % (zlib.crc32(text.encode()) & 0xFFFF)


def _route(to: str | None, sender: str) -> bytes:
    return (FLEET.encode() if to is None else _tag(to)) + b":" + _tag(host_of(sender))


def _mac(key: bytes, to: str | None, sender: str, signed: bytes) -> bytes:
    bound = b"%s%s\0%s\0" % (
        _LABEL,
        (FLEET if to is None else to).encode(),
        host_of(sender).encode(),
    )
    digest = hmac.digest(key, bound + signed, "sha256")[:MAC_BYTES]
    return base64.urlsafe_b64encode(digest)[:MAC_CHARS]


def seal(
    data: bytes, key: bytes, counter: int, *, to: str | None = None, sender: str = ""
) -> bytes:
    """`data` with the seal line added, bound to its recipient `to` (a robot id; None: the
    whole fleet, by multicast) and to the sender's own IP address `sender`; ValueError if it
    has no header end or grows too big."""
    if not 1 <= counter <= MAX_COUNTER:
        raise ValueError(f"counter must be 1..{MAX_COUNTER}, not {counter}")
    end = data.find(b"\r\n\r\n")
    if end < 0:
        raise ValueError("not an SDfR datagram: no end of headers")
    head, rest = data[: end + 2], data[end + 2 :]
    prefix = b"%s%s %d %s " % (AUTH_HEADER, key_id(key).encode(), counter, _route(to, sender))
    mac = _mac(key, to, sender, head + prefix + rest)
    out = b"".join((head, prefix, mac, b"\r\n", rest))
    if len(out) > MAX_DATAGRAM:
        raise ValueError(f"sealed datagram would be {len(out)} bytes, more than {MAX_DATAGRAM}")
    return out


def _seal_line(data: bytes) -> tuple[int, str, int, bytes, bytes] | Reject | None:
    """The seal of a datagram as written (not checked): where its line ends, key id, counter,
    route, mac; None when there is none, a Reject when it is malformed."""
    end = data.find(b"\r\n\r\n")
    start = data.rfind(b"\n", 0, end) + 1 if end > 0 else 0
    if end < 0 or not data.startswith(AUTH_HEADER, start):
        if AUTH_HEADER[:-1] in data[: end if end >= 0 else len(data)]:
            return Reject("bad-seal", "X-SDFR-AUTH is not the last header line")
        return None
    fields = data[start + len(AUTH_HEADER) : end].split(b" ")
    if len(fields) != 4:
        return Reject("bad-seal", _SEAL_FORM)
    kid, ctr, route, mac = fields
    to, colon, sender = route.partition(b":")
    if (
        len(kid) != KID_CHARS
        or not _HEX.issuperset(kid)
        or not 0 < len(ctr) <= 16
        or not ctr.isdigit()
        or not colon
        or not (to == b"*" or (len(to) == TAG_CHARS and _HEX.issuperset(to)))
        or len(sender) != TAG_CHARS
        or not _HEX.issuperset(sender)
        or len(mac) != MAC_CHARS
        or not _B64URL.issuperset(mac)
    ):
        return Reject("bad-seal", _SEAL_FORM)
    counter = int(ctr)
    if not 1 <= counter <= MAX_COUNTER:
        return Reject("bad-seal", f"counter {counter} out of range")
    return end, kid.decode(), counter, route, mac


_SEAL_FORM = "X-SDFR-AUTH is not '<key id> <counter> <to>:<from> <mac>'"


def seal_of(data: bytes) -> Sealed | None:
    """The key id and counter a datagram's seal names, *unchecked* (for captures: whoever
    reads a pcap needs no key to see which key a robot used)."""
    line = _seal_line(data)
    return Sealed(line[1], line[2], line[3][:1] == b"*") if isinstance(line, tuple) else None


def check(data: bytes, keyring: Keyring, *, me: str = "", src: str = "") -> Sealed | Reject | None:
    """Check the seal of a datagram that robot `me` received from the IP address `src`,
    before anything else reads it.

    Returns the seal when it is valid, None for an unsigned datagram the keyring lets through,
    and a Reject otherwise: "not-for-me" when it was sealed for another robot, "relayed" when
    its sender sealed it with another address than the one it came from.  Only the seal line
    is looked at; nothing else is parsed.
    """
    line = _seal_line(data)
    if line is None:
        if keyring.accepts_unsigned:
            return None
        return Reject("unsigned", "the fleet is keyed and the datagram carries no seal")
    if isinstance(line, Reject):
        return line
    end, kid, counter, route, mac = line
    key = keyring.keys.get(kid)
    if key is None:
        return Reject("unknown-key", f"sealed with key {kid}, not in the keyring")
    to, _, sender = route.partition(b":")
    fleet = to == b"*"
    if not fleet and to != _tag(me):
        return Reject("not-for-me", "sealed for another robot")
    if sender != _tag(host_of(src)):
        return Reject("relayed", f"sealed by another address than {src}")
    signed = data[: end - MAC_CHARS] + data[end + 2 :]
    if not hmac.compare_digest(_mac(key, None if fleet else me, src, signed), mac):
        return Reject("bad-mac", f"seal of key {kid} does not match")
    return Sealed(kid, counter, fleet)


WINDOW = 64
_MASK = (1 << WINDOW) - 1


@dataclass(slots=True)
class ReplayWindow:
    """The counters seen from one sender's boot: the highest, and which of the 63 below it.

    A counter above the highest is new; one more than WINDOW below it, or seen already, is a
    replay (or so late that it must be treated as one).
    """

    boot: int = -1
    top: int = 0
    seen: int = 0  # bit i: counter top - i was accepted

    def fresh(self, boot: int, counter: int) -> bool:
        """Whether (boot, counter) has not been accepted; a boot other than ours is new."""
        if boot != self.boot or counter > self.top:
            return True
        back = self.top - counter
        return back < WINDOW and not (self.seen >> back) & 1

    def reset(self) -> None:
        """Forget what was seen: the next counter of any boot is new."""
        self.boot, self.top, self.seen = -1, 0, 0

    def accept(self, boot: int, counter: int) -> None:
        if boot != self.boot:
            self.boot, self.top, self.seen = boot, counter, 1
        elif counter > self.top:
            self.seen = ((self.seen << (counter - self.top)) | 1) & _MASK
            self.top = counter
        else:
            self.seen |= 1 << (self.top - counter)
