"""Address self-configuration as a timed automaton with no I/O.

A robot of fleet F takes `10.F.x.y`, with x and y derived from its MAC
(`candidates`), checks with ARP probes that nobody uses it before taking it
and announces it after, in the spirit of RFC 5227, and keeps watching: a
merge of two groups can put two robots on one address at any time.

Conflicts are settled the same way on both robots, so exactly one moves:
- before the address is ours (probing), any sign that someone else uses or
  probes it makes us try the next candidate — we never take a used address;
- once it is ours, the robot with the lower MAC keeps it (and defends it
  with an announcement); the other releases it and probes its next
  candidate. The rule cannot ping-pong: the keeper never moves and the
  mover never comes back to an address it lost.
After `max_conflicts` conflicts in a row the next attempts are rate-limited.
Whatever an outsider keeps answering, the machine's memory is bounded: the last
CONFLICTS_KEPT conflicts are kept (and all counted), the last LOST_KEPT addresses
lost, and the candidate sequence needs a fixed bitmap.

Like `sdfr.protocol`, everything takes `now`; randomness comes from an
injected `random.Random`; the adapter owns the raw socket and the kernel.
"""

from __future__ import annotations

import enum
import hashlib
import ipaddress
import math
import random
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from ipaddress import IPv4Address

PREFIX_LEN = 16
#: Conflicts remembered (for the status and the log); older ones are only counted.
CONFLICTS_KEPT = 32
#: Addresses lost to a lower MAC that are skipped when the candidate sequence starts over.
LOST_KEPT = 64
#: Addresses in a fleet's sequence: 10.<fleet>.<x>.<y> with x and y in 1..254.
SPACE = 254 * 254


def mac_bytes(mac: str) -> bytes:
    try:
        raw = bytes.fromhex(mac.replace(":", "").replace("-", ""))
    except ValueError:
        raw = b""
    if len(raw) != 6:
        raise ValueError(f"not a MAC address: {mac!r}")
    return raw


def _octet(v: int) -> int:
    """0..255 into 1..254: x and y are never 0 or 255 (network and broadcast of a /24)."""
    return 1 + v % 254


def candidates(fleet: int, mac: str) -> Iterator[IPv4Address]:
    """The addresses a robot tries, in order: `10.<fleet>.<x>.<y>`.

    The first takes x and y from the MAC's last two octets (`x = 1 + o5 % 254`,
    `y = 1 + o6 % 254`), so an operator can read a robot's address off its
    label and two MACs ending alike collide on purpose in tests. The k-th
    after it takes the first two bytes of SHA-256(MAC || k), mapped the same
    way; addresses already in the sequence are skipped. Every robot computes
    the same sequence for the same MAC. Once all SPACE addresses have come,
    it starts over: a robot pushed off address after address keeps trying
    (the addresses seen take a fixed 8 KiB bitmap).
    """
    if not 0 <= fleet <= 255:
        raise ValueError(f"fleet must be 0-255, got {fleet}")
    raw = mac_bytes(mac)
    while True:
        seen = bytearray(8192)  # bit x * 256 + y: 10.<fleet>.x.y came already
        given = 0
        k = 0
        while given < SPACE:
            if k == 0:
                a, b = raw[4], raw[5]
            else:
                digest = hashlib.sha256(raw + k.to_bytes(4, "big")).digest()
                a, b = digest[0], digest[1]
            k += 1
            x, y = _octet(a), _octet(b)
            bit = x << 8 | y
            if seen[bit >> 3] & 1 << (bit & 7):
                continue
            seen[bit >> 3] |= 1 << (bit & 7)
            given += 1
            yield IPv4Address(f"10.{fleet}.{x}.{y}")


class State(enum.Enum):
    IDLE = "idle"
    PROBING = "probing"
    ANNOUNCING = "announcing"
    BOUND = "bound"
    WAITING = "waiting"  # rate-limited after too many conflicts


@dataclass(frozen=True, slots=True)
class AddrConfig:
    """Timers in seconds. RFC 5227's are PROBE_WAIT 1, PROBE_NUM 3, PROBE_MIN 1, PROBE_MAX 2,
    ANNOUNCE_WAIT 2, ANNOUNCE_NUM 2, ANNOUNCE_INTERVAL 2, MAX_CONFLICTS 10,
    RATE_LIMIT_INTERVAL 60, DEFEND_INTERVAL 10; a robot fleet on one radio hop can be faster."""

    fleet: int
    mac: str
    probe_wait: float = 0.2
    probe_num: int = 3
    probe_min: float = 0.1
    probe_max: float = 0.2
    announce_wait: float = 0.2
    announce_num: int = 2
    announce_interval: float = 0.2
    max_conflicts: int = 10
    rate_limit_interval: float = 60.0
    defend_interval: float = 10.0
    refresh_interval: float = 1.0


@dataclass(frozen=True, slots=True)
class Arp:
    """An ARP packet seen on the link (op 1 request, 2 reply)."""

    op: int
    sender_mac: str
    sender_ip: IPv4Address
    target_ip: IPv4Address


@dataclass(frozen=True, slots=True)
class ArpSend:
    """An ARP packet to send: a probe (sender 0.0.0.0) or an announcement (sender = target)."""

    kind: str  # "probe" | "announce"
    ip: IPv4Address


@dataclass(frozen=True, slots=True)
class Assign:
    ip: IPv4Address


@dataclass(frozen=True, slots=True)
class Release:
    ip: IPv4Address


Action = Assign | Release
ZERO = IPv4Address("0.0.0.0")


@dataclass(frozen=True, slots=True)
class Conflict:
    """One settled conflict, for logs and counters."""

    time: float
    ip: IPv4Address
    other_mac: str
    kept: bool  # we kept the address (we had the lower MAC, or it was not ours yet: False)
    phase: str


class Addressing:
    """One robot's address on one link."""

    def __init__(self, config: AddrConfig, rng: random.Random) -> None:
        self.config = config
        self.mac = ":".join(f"{b:02x}" for b in mac_bytes(config.mac))
        self.rng = rng
        self.state = State.IDLE
        self.ip: IPv4Address | None = None  # the candidate being probed, announced or held
        #: The last CONFLICTS_KEPT conflicts, oldest first; `conflicts_total` counts them all.
        self.conflicts: deque[Conflict] = deque(maxlen=CONFLICTS_KEPT)
        self.conflicts_total = 0
        self._candidates = candidates(config.fleet, self.mac)
        #: Addresses lost to a lower MAC, the last LOST_KEPT, oldest first (a dict: ordered).
        self._lost: dict[IPv4Address, None] = {}
        self._streak = 0
        self._sent = 0
        self._deadline = math.inf
        self._last_defend = -math.inf
        self._last_refresh = -math.inf
        self._arp: list[ArpSend] = []
        self._actions: list[Action] = []

    # -- inputs ----------------------------------------------------------------------------

    def start(self, now: float, current: IPv4Address | None = None) -> None:
        """Begin; `current` is an address of ours already on the link (a daemon restart)."""
        if current is not None and current in self._first(32):
            # Ours a moment ago: announce it again at once rather than giving it up.
            self.ip = current
            self._enter_announcing(now, wait=0.0)
            return
        self._next_candidate(now)

    def handle_arp(self, pkt: Arp, now: float) -> None:
        """An ARP packet from the link (our own are ignored)."""
        if pkt.sender_mac.lower() == self.mac or self.ip is None:
            return
        ip = self.ip
        if self.state is State.PROBING:
            # Someone uses it (any packet from it), or probes for it at the same time.
            used = pkt.sender_ip == ip
            probed = pkt.op == 1 and pkt.sender_ip == ZERO and pkt.target_ip == ip
            if used or probed:
                if probed and not used and pkt.sender_mac.lower() > self.mac:
                    # Two probes at once: the same rule on both sides lets the lower MAC go on.
                    return
                self._conflict(now, pkt.sender_mac, kept=False, phase="probe")
                self._next_candidate(now)
            return
        if self.state in (State.ANNOUNCING, State.BOUND) and pkt.sender_ip == ip:
            self._settle(now, pkt.sender_mac)

    def suspect(self, now: float) -> None:
        """Something else (a datagram from our own address) suggests a conflict: announce,
        so that the other robot's ARP, and ours, settle it."""
        if self.state is State.BOUND and now - self._last_defend >= self.config.defend_interval:
            self._defend(now)

    def refresh(self, now: float) -> None:
        """New robots came into range (two groups merging, say): announce our address once,
        at most every `refresh_interval`, so that a robot of the other group holding the
        same address hears of it now and not whenever ARP traffic happens to reveal it."""
        if self.state is State.BOUND and now - self._last_refresh >= self.config.refresh_interval:
            assert self.ip is not None
            self._last_refresh = now
            self._arp.append(ArpSend("announce", self.ip))

    def handle_timer(self, now: float) -> None:
        if now < self._deadline:
            return
        cfg = self.config
        if self.state is State.PROBING:
            assert self.ip is not None
            if self._sent < cfg.probe_num:
                self._arp.append(ArpSend("probe", self.ip))
                self._sent += 1
                if self._sent < cfg.probe_num:
                    self._deadline = now + self.rng.uniform(cfg.probe_min, cfg.probe_max)
                else:
                    self._deadline = now + cfg.announce_wait
                return
            self._enter_announcing(now, wait=0.0)
            self._actions.append(Assign(self.ip))
            self.handle_timer(now)
        elif self.state is State.ANNOUNCING:
            assert self.ip is not None
            self._arp.append(ArpSend("announce", self.ip))
            self._sent += 1
            if self._sent >= cfg.announce_num:
                self.state = State.BOUND
                self._streak = 0
                self._deadline = math.inf
            else:
                self._deadline = now + cfg.announce_interval
        elif self.state is State.WAITING:
            self._begin_probe(now, wait=0.0)

    def next_deadline(self) -> float | None:
        return None if self._deadline == math.inf else self._deadline

    # -- outputs ---------------------------------------------------------------------------

    def arp_to_send(self) -> list[ArpSend]:
        out, self._arp = self._arp, []
        return out

    def actions(self) -> list[Action]:
        out, self._actions = self._actions, []
        return out

    @property
    def bound(self) -> IPv4Address | None:
        """The address in use now (announcing or held)."""
        return self.ip if self.state in (State.ANNOUNCING, State.BOUND) else None

    @property
    def network(self) -> ipaddress.IPv4Network:
        return ipaddress.IPv4Network(f"10.{self.config.fleet}.0.0/{PREFIX_LEN}")

    # -- internals -------------------------------------------------------------------------

    def _first(self, n: int) -> list[IPv4Address]:
        seq = candidates(self.config.fleet, self.mac)
        return [next(seq) for _ in range(n)]

    def _settle(self, now: float, other_mac: str) -> None:
        """Our address is claimed by another MAC: the lower MAC keeps it."""
        assert self.ip is not None
        if self.mac < other_mac.lower():
            self._conflict(now, other_mac, kept=True, phase="held")
            if now - self._last_defend >= self.config.defend_interval:
                self._defend(now)
            return
        self._conflict(now, other_mac, kept=False, phase="held")
        self._lost.pop(self.ip, None)
        self._lost[self.ip] = None
        if len(self._lost) > LOST_KEPT:
            del self._lost[next(iter(self._lost))]
        self._actions.append(Release(self.ip))
        self._next_candidate(now)

    def _defend(self, now: float) -> None:
        assert self.ip is not None
        self._last_defend = now
        self._arp.append(ArpSend("announce", self.ip))

    def _conflict(self, now: float, other_mac: str, *, kept: bool, phase: str) -> None:
        assert self.ip is not None
        self.conflicts.append(Conflict(now, self.ip, other_mac.lower(), kept, phase))
        self.conflicts_total += 1
        if not kept:
            self._streak += 1

    def _next_candidate(self, now: float) -> None:
        ip = next(self._candidates)
        while ip in self._lost:
            ip = next(self._candidates)
        self.ip = ip
        if self._streak >= self.config.max_conflicts:
            self.state = State.WAITING
            self._deadline = now + self.config.rate_limit_interval
            return
        self._begin_probe(now, wait=self.rng.uniform(0, self.config.probe_wait))

    def _begin_probe(self, now: float, *, wait: float) -> None:
        self.state = State.PROBING
        self._sent = 0
        self._deadline = now + wait

    def _enter_announcing(self, now: float, *, wait: float) -> None:
        self.state = State.ANNOUNCING
        self._sent = 0
        self._deadline = now + wait
