"""The discovery protocol as a timed automaton with no I/O.

The owner of the sockets feeds it datagrams (`receive`) and the time
(`handle_timer`), takes what it must send (`datagrams_to_send`) and sleeps
until `next_deadline()`. Every entry point takes `now` in seconds of one
monotonic clock; randomness (reply delays, beacon jitter) comes from the
injected `random.Random`. Nothing here reads a clock or touches a socket, so
whole fleets run in virtual time in the tests.

Messages (see sdfr.wire):
- Discovery (M-SEARCH): multicast at start-up, asking every robot for its
  services; unicast to one robot as a ping (`seq`) or to fetch a service set
  (or some parts of it) whose version we do not hold.
- Response (200 OK): the unicast answer to a ping, and to plain SSDP clients.
- Update (NOTIFY ssdp:update): the service set, split into parts; multicast
  when local services change, in reply to a Discovery otherwise.
- Alive (NOTIFY ssdp:alive): the beacon, carrying only the set's version and
  digest, so a robot whose services did not change costs a few hundred bytes.
- Byebye (NOTIFY ssdp:byebye): graceful departure.

Trust (see also sdfr.auth):
- With a fleet key every datagram goes out sealed; one whose seal fails is dropped before it
  is parsed, and one whose counter was seen already in that boot (a replay) right after.
- A claim that contradicts what a robot last proved is never applied on the word of one
  datagram: an older boot, a datagram after that boot's Byebye, an older version, a new
  address.  It is answered with a *challenge*, a ping to the address it came from, and the
  robot's answer to that (its boot, version and digest, fresh by construction) is what is
  believed.  So nothing is ever locked out for good.
- A robot heard only through unsigned datagrams is *unproven* until it answers a ping: it is
  challenged at once (and again every ping timeout while it stays unproven), neither saved
  nor listed, and forgotten after a miss limit of silence.  At most MAX_UNPROVEN of them are
  held, and MAX_PEERS robots in all.
- An address that has not answered a ping of ours never gets more bytes than it sent: its
  unicast fetch waits for its answer to a challenge, and its multicast search is answered by
  multicast, at most once every MCAST_SET_GAP.  Work is bounded per source address
  (SOURCE_RATE), and challenges in all (CHALLENGE_RATE).
"""

from __future__ import annotations

import math
import random
from collections import Counter, deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from urllib.parse import urlsplit

from sdfr import auth, wire
from sdfr.auth import OPEN, Keyring, ReplayWindow, Sealed
from sdfr.limits import KeyedBuckets, TokenBucket
from sdfr.model import PeerRecord, Service, service_digest
from sdfr.wire import WANT_ALL, Alive, Byebye, Discovery, Origin, Reject, Response, Update

#: A unicast destination; `None` in an outgoing datagram means the multicast group.
Addr = tuple[str, int]
Outgoing = tuple[bytes, Addr | None]


#: Robots the history map holds at most; when full, the one silent longest is forgotten.
MAX_PEERS = 1024
#: Robots heard (unsigned) but never proven by a round trip, held at most.
MAX_UNPROVEN = 256
#: Update parts buffered for unproven robots, shared among them (but at least
#: UNPROVEN_PARTS_MIN each); the rest is fetched once a robot is proven.
UNPROVEN_PARTS = 512
UNPROVEN_PARTS_MIN = 4
#: Challenges sent at most, per second and in a burst, to all addresses together.
CHALLENGE_RATE = 20.0
CHALLENGE_BURST = 128.0
#: Datagrams read from one source address, per second and in a burst; the rest are dropped
#: unread.  A whole set of 255 parts fits in the burst.
SOURCE_RATE = 500.0
SOURCE_BURST = 1000.0
MAX_SOURCES = 4096
#: Plain SSDP searches answered at most, per second and in a burst (ssdp_interop).
PLAIN_RATE = 10.0
PLAIN_BURST = 20.0
#: Whole sets multicast in answer to searches at most once in this many seconds.
MCAST_SET_GAP = 1.0
#: Update parts one address is served at most, per second, in whole sets of ours.
FETCH_SETS_PER_S = 2.0
#: Searchers one multicast answer collects at most.
MAX_REPLY_TO = 64


#: The product's protocol defaults, written here once: `CoreConfig` and sdfrd's `Config`
#: (its flags, TOML keys and help) take them from here.
BEACON_INTERVAL = 10.0  # the paper's
MISS_LIMIT = 3
PING_WINDOW = 20
REPLY_DELAY_MAX = 0.5


@dataclass(frozen=True, slots=True)
class CoreConfig:
    """Protocol timing; the defaults are the product's (the paper's 10 s beacon).  sdfrd
    builds it from its `Config` by field name (`Config.core_config`)."""

    fleet: int
    robot_id: str
    beacon_interval: float = BEACON_INTERVAL
    miss_limit: int = MISS_LIMIT
    ping_interval: float = BEACON_INTERVAL
    ping_window: int = PING_WINDOW
    reply_delay_max: float = REPLY_DELAY_MAX
    mx: int = 1
    jitter: float = 0.1
    update_coalesce: float = 0.02
    fetch_wait: float = 0.25
    group: str = wire.DEFAULT_GROUP
    port: int = wire.DEFAULT_PORT
    #: Answer plain SSDP clients' searches; None: only while the fleet has no key.
    ssdp_interop: bool | None = None

    @property
    def dead_after(self) -> float:
        """Silence after which a peer is unreachable."""
        return self.miss_limit * self.beacon_interval

    @property
    def ping_timeout(self) -> float:
        return min(1.0, 0.8 * self.ping_interval)

    @property
    def max_age(self) -> int:
        return max(1, math.ceil(self.dead_after))

    @property
    def proven_for(self) -> float:
        """How long an answered ping vouches for its address."""
        return max(2 * self.ping_interval, self.dead_after)


@dataclass(slots=True)
class _Fetch:
    """Reassembly of one peer's service set (one boot and version)."""

    boot_id: int
    version: int
    digest: str
    parts: int = 0
    got: dict[int, tuple[Service, ...]] = field(default_factory=dict)
    retry_at: float = 0.0
    backoff: float = 0.0

    def missing(self) -> tuple[int, ...]:
        return tuple(i for i in range(self.parts) if i not in self.got)


@dataclass(frozen=True, slots=True)
class _Ping:
    """A ping in flight.  The answer to a challenge is believed whole: boot, version, digest,
    and the address it came from."""

    robot_id: str
    sent: float
    addr: Addr
    challenge: bool = False


@dataclass(slots=True)
class Peer:
    """What this robot knows of another: the history map's entry, plus protocol timers."""

    robot_id: str
    address: Addr
    location: str
    first_seen: float
    last_heard: float
    boot_id: int
    version: int
    digest: str
    reachable: bool = False
    #: Answered a ping of ours, or spoke with a valid seal: saved, listed and pinged.
    proven: bool = False
    #: (boot, version, digest) the `services` below belong to; None when we hold no set.
    held: tuple[int, int, str] | None = None
    services: tuple[Service, ...] = ()
    byebye_boot: int | None = None
    pings: deque[bool] = field(default_factory=deque)
    rtt: float | None = None
    next_ping: float = math.inf
    fetch: _Fetch | None = None
    window: ReplayWindow = field(default_factory=ReplayWindow)
    challenged_at: float = -math.inf
    #: A fetch it asked for before its address was proven: (address, parts wanted or None).
    deferred: tuple[Addr, tuple[int, ...] | None] | None = None

    @property
    def current(self) -> bool:
        """We hold the service set the peer last announced."""
        return self.held == (self.boot_id, self.version, self.digest)

    @property
    def indicator(self) -> float | None:
        """Success rate of the pings in the window; None before the first ping is settled."""
        if not self.pings:
            return None
        return sum(self.pings) / len(self.pings)


@dataclass(slots=True)
class Conflict:
    """Another sender claiming our robot id: a second daemon, or a forger."""

    address: str
    boot_id: int
    last_seen: float
    count: int = 1


@dataclass(slots=True)
class Counters:
    datagrams_in: Counter[str] = field(default_factory=Counter)
    datagrams_out: Counter[str] = field(default_factory=Counter)
    bytes_in: int = 0
    bytes_out: int = 0
    rejects: Counter[str] = field(default_factory=Counter)
    #: Datagrams whose seal checked out, by key id.
    verified: Counter[str] = field(default_factory=Counter)
    challenges: int = 0
    #: Challenges not sent for want of budget (CHALLENGE_RATE): a sign of a flood.
    challenges_limited: int = 0


_KIND = {Discovery: "discovery", Response: "response", Update: "update", Alive: "alive"}


class Core:
    """One robot's discovery protocol."""

    def __init__(
        self,
        config: CoreConfig,
        *,
        boot_id: int,
        rng: random.Random,
        location: str = "",
        version: int = 0,
        services: Sequence[Service] = (),
        keyring: Keyring = OPEN,
    ) -> None:
        self.config = config
        self.boot_id = boot_id
        self.location = location
        self.rng = rng
        self.version = version
        self.services: tuple[Service, ...] = tuple(services)
        self.digest = service_digest(self.services)
        self.keyring = keyring
        self.peers: dict[str, Peer] = {}
        self._unproven = 0  # peers not proven (of self.peers)
        self.counters = Counters()
        #: The latest sender claiming our robot id, if any.
        self.conflict: Conflict | None = None
        #: Why our set cannot be announced (too many parts), while it cannot.
        self.announce_error: str | None = None
        self._out: list[Outgoing] = []
        self._dirty: set[str] = set()
        self._removed: set[str] = set()
        #: Address -> when a ping to it was last answered (a round trip proven).
        self._answered: dict[Addr, float] = {}
        #: How many times a peer became reachable (a merge or an arrival shows here).
        self.arrivals = 0
        self._started = False
        self._stopped = False
        self._next_beacon = math.inf
        self._next_prune = math.inf
        self._discovery_repeat = math.inf
        self._update_at = math.inf
        self._reply_at = math.inf
        #: Searchers waiting for our set: address -> robot id.
        self._reply_to: dict[Addr, str] = {}
        self._last_set_multicast = -math.inf
        self._pings: dict[int, _Ping] = {}
        self._ping_seq = rng.randrange(1 << 30)
        self._sent_seals = 0
        self._sources = KeyedBuckets(SOURCE_RATE, SOURCE_BURST, MAX_SOURCES)
        self._fetch_budget = KeyedBuckets(1.0, 1.0, MAX_SOURCES)
        self._challenge_budget = TokenBucket(CHALLENGE_RATE, CHALLENGE_BURST)
        self._plain_budget = TokenBucket(PLAIN_RATE, PLAIN_BURST)
        self._own_challenge_at = -math.inf
        self._parts_cache: tuple[tuple[int, int, str, str], list[bytes]] | None = None
        #: The set every robot in range last heard by multicast: the base of the next delta.
        self._announced: tuple[int, tuple[Service, ...]] | None = None

    # -- life cycle ------------------------------------------------------------------------

    @property
    def started(self) -> bool:
        return self._started

    def start(self, now: float) -> None:
        """Announce ourselves and ask who is there."""
        self._started = True
        self._search(now)
        self._send_update_parts(None, now)
        # A second search covers a lost first one; beacons cover the rest.
        self._discovery_repeat = now + self.config.reply_delay_max + self.rng.uniform(0.2, 0.5)
        self._next_beacon = now + self._beacon_period()
        self._next_prune = now + self.config.proven_for

    def stop(self, now: float) -> None:
        """Say goodbye; nothing is sent after this."""
        if self._started and not self._stopped:
            self._send(Byebye(self._origin()), None)
        self._stopped = True

    # -- inputs ----------------------------------------------------------------------------

    def set_keyring(self, keyring: Keyring) -> None:
        """The fleet keyring changed (a key installed, put to use or removed; the mode)."""
        self.keyring = keyring

    def set_location(self, location: str, now: float | None = None) -> None:
        """Our address (so LOCATION) changed; with `now`, tell the fleet at once."""
        self.location = location
        self._parts_cache = None
        if now is not None and self._started and not self._stopped:
            # Peers key us by robot id and take the new address from this datagram.
            self._send(Alive(self._origin(), self.location, self.config.max_age), None)
            # Questions asked from the old address (say, one that another robot also held)
            # may have gone nowhere: ask again now rather than after their back-off.
            for peer in self.peers.values():
                if peer.fetch is not None:
                    peer.fetch.backoff = 0.0
                    peer.fetch.retry_at = now

    def set_services(self, version: int, services: Sequence[Service], now: float) -> None:
        """The local registrations changed: announce the new set (coalescing bursts)."""
        if version == self.version and tuple(services) == self.services:
            return
        self.version = version
        self.services = tuple(services)
        self.digest = service_digest(self.services)
        if self._started and not self._stopped:
            self._update_at = min(self._update_at, now + self.config.update_coalesce)

    def restore(self, views: Iterable[PeerRecord]) -> None:
        """Load the history map saved by an earlier run; every peer starts unreachable."""
        for v in views:
            if v.robot_id == self.config.robot_id:
                continue
            held = (
                (v.boot_id, v.version, v.digest) if service_digest(v.services) == v.digest else None
            )
            self.peers[v.robot_id] = Peer(
                robot_id=v.robot_id,
                address=(v.address, self.config.port),
                location=v.location,
                first_seen=v.first_seen,
                last_heard=v.last_seen,
                boot_id=v.boot_id,
                version=v.version,
                digest=v.digest,
                reachable=False,
                proven=True,  # only proven robots are saved
                held=held,
                services=v.services if held else (),
                rtt=None if v.rtt_ms is None else v.rtt_ms / 1000,
            )

    def receive(self, data: bytes, src: Addr, now: float) -> None:
        """A datagram arrived from `src`."""
        self.counters.bytes_in += len(data)
        if not self._sources.take(src[0], now):
            self.counters.rejects["rate-limited"] += 1
            return
        seal = auth.check(data, self.keyring)
        if isinstance(seal, Reject):
            if seal.reason == "unsigned" and self._plain_search_allowed(data):
                seal = None  # a plain SSDP client's search: read-only, answered below
            else:
                self.counters.rejects[seal.reason] += 1
                return
        msg = wire.decode(data, fleet=self.config.fleet)
        if isinstance(msg, Reject):
            self.counters.rejects[msg.reason] += 1
            return
        if self._stopped:
            return
        self.counters.datagrams_in[_KIND.get(type(msg), "byebye")] += 1
        if seal is not None:
            self.counters.verified[seal.kid] += 1
        if isinstance(msg, Discovery) and msg.st not in self._targets():
            self.counters.rejects["other-target"] += 1
            return
        if isinstance(msg, Discovery) and msg.origin is None:
            self._on_plain_search(msg, src, now)
            return
        origin = msg.origin
        assert origin is not None
        if origin.robot_id == self.config.robot_id:
            self._on_own_id(msg, origin, src, seal, now)
            return
        if isinstance(msg, Byebye) and origin.robot_id not in self.peers:
            return  # a robot we never knew leaves: nothing to do
        proof = self._is_proof(msg, origin, src)
        peer, refused = self._gate(origin, src, now, seal, proof)
        if isinstance(msg, Discovery):
            self._on_discovery(msg, peer, src, now, answer_ping=refused != "replay")
            return
        if peer is None:
            return
        if isinstance(msg, Byebye):
            self._on_byebye(peer)
            return
        self._heard(peer, origin, src, now, getattr(msg, "location", None), proof)
        soon = False
        if isinstance(msg, Update):
            # More parts of a whole set are normally right behind this one; a delta we
            # could not apply will not be followed by anything that helps.
            soon = msg.base is None
            self._on_update(peer, msg, now)
        elif isinstance(msg, Response):
            self._on_response(peer, msg, src, now)
        if peer.robot_id in self.peers:
            self._want_current(peer, now, soon=soon)

    def handle_timer(self, now: float) -> None:
        """Do whatever is due at `now`."""
        if not self._started or self._stopped:
            return
        cfg = self.config
        if now >= self._discovery_repeat:
            self._discovery_repeat = math.inf
            self._search(now)
        if now >= self._update_at:
            self._update_at = math.inf
            self._announce_change(now)
        if now >= self._reply_at:
            self._flush_replies(now)
        if now >= self._next_beacon:
            self._send(Alive(self._origin(), self.location, cfg.max_age), None)
            self._next_beacon = now + self._beacon_period()
        if now >= self._next_prune:
            self._prune(now)
        expired = [seq for seq, p in self._pings.items() if now >= p.sent + cfg.ping_timeout]
        for seq in expired:
            ping = self._pings.pop(seq)
            peer = self.peers.get(ping.robot_id)
            if peer is not None and ping.addr == peer.address:
                # (A challenge to another address says nothing of the peer's link.)
                self._settle_ping(peer, ok=False)
        for peer in list(self.peers.values()):
            if not peer.proven and now >= peer.last_heard + cfg.dead_after:
                self._forget(peer)
                continue
            if peer.reachable and now >= peer.last_heard + cfg.dead_after:
                peer.reachable = False
                peer.next_ping = math.inf
                peer.fetch = None
                self._dirty.add(peer.robot_id)
                continue
            if peer.reachable and now >= peer.next_ping:
                if peer.proven:
                    self._ping(peer, now)
                else:
                    self._challenge(peer, peer.address, now)
                    peer.next_ping = max(peer.next_ping, now + 1.0 / CHALLENGE_RATE)
            if peer.fetch is not None and now >= peer.fetch.retry_at:
                self._request_fetch(peer, now)

    def next_deadline(self) -> float | None:
        """When `handle_timer` must run next (None: only an input can change anything)."""
        if not self._started or self._stopped:
            return None
        cfg = self.config
        t = min(
            self._next_beacon,
            self._discovery_repeat,
            self._update_at,
            self._reply_at,
            self._next_prune,
        )
        for ping in self._pings.values():
            t = min(t, ping.sent + cfg.ping_timeout)
        for peer in self.peers.values():
            if peer.reachable:
                t = min(t, peer.last_heard + cfg.dead_after, peer.next_ping)
            elif not peer.proven:
                t = min(t, peer.last_heard + cfg.dead_after)
            if peer.fetch is not None:
                t = min(t, peer.fetch.retry_at)
        return None if t == math.inf else t

    # -- outputs ---------------------------------------------------------------------------

    def datagrams_to_send(self) -> list[Outgoing]:
        out, self._out = self._out, []
        return out

    def round_trip_proven(self, addr: Addr, now: float) -> bool:
        """Whether a ping to `addr` was answered within the last two ping intervals: what
        goes there now can tell the kernel the neighbour is reachable (``MSG_CONFIRM``), so
        it does not probe it with ARP while the pings keep coming back."""
        t = self._answered.get(addr)
        return t is not None and now - t <= 2 * self.config.ping_interval

    @property
    def has_dirty(self) -> bool:
        return bool(self._dirty) or bool(self._removed)

    def take_dirty(self) -> list[PeerRecord]:
        """Proven peers whose stored view changed since the last call."""
        views = [
            self.view(self.peers[r])
            for r in sorted(self._dirty)
            if r in self.peers and self.peers[r].proven
        ]
        self._dirty.clear()
        return views

    def mark_unsaved(self, robot_ids: Iterable[str], removed: Iterable[str]) -> None:
        """Views taken but not saved (the disk was full): give them back for the next save."""
        self._dirty.update(r for r in robot_ids if r in self.peers)
        self._removed.update(removed)

    def take_removed(self) -> list[str]:
        """Robots forgotten since the last call (the history map was full): unsave them."""
        removed = sorted(self._removed)
        self._removed.clear()
        return removed

    def view(self, peer: Peer) -> PeerRecord:
        return PeerRecord(
            robot_id=peer.robot_id,
            address=peer.address[0],
            location=peer.location,
            boot_id=peer.boot_id,
            version=peer.version,
            digest=peer.digest,
            reachable=peer.reachable,
            first_seen=peer.first_seen,
            last_seen=peer.last_heard,
            indicator=peer.indicator,
            rtt_ms=None if peer.rtt is None else round(peer.rtt * 1000, 3),
            pings=len(peer.pings),
            services=peer.services,
        )

    def reachable(self) -> list[str]:
        """Robots reachable now and proven (those a robot lists)."""
        return sorted(r for r, p in self.peers.items() if p.reachable and p.proven)

    @property
    def ssdp_interop(self) -> bool:
        return auth.plain_ssdp_answered(self.config.ssdp_interop, self.keyring)

    # -- trust -----------------------------------------------------------------------------

    def _gate(
        self, origin: Origin, src: Addr, now: float, seal: Sealed | None, proof: bool
    ) -> tuple[Peer | None, str | None]:
        """The peer a datagram speaks for, or None and why it must not be believed.

        Freshness: a sealed datagram's counter must be new for its boot.  Claims that
        contradict what the peer last proved (see the module's notes) are answered with a
        challenge instead of being applied, unless this datagram is itself such an answer.
        """
        peer = self.peers.get(origin.robot_id)
        if peer is None:
            refused = self._admit(seal is not None, now)
            if refused is not None:
                return self._refuse(refused)
            peer = self.peers[origin.robot_id] = Peer(
                robot_id=origin.robot_id,
                address=src,
                location="",
                first_seen=now,
                last_heard=now,
                boot_id=origin.boot_id,
                version=origin.version,
                digest=origin.digest,
                proven=seal is not None,
            )
            if seal is not None:
                peer.window.accept(origin.boot_id, seal.counter)
            else:
                self._unproven += 1
                self._challenge(peer, src, now)
            return peer, None
        if (
            seal is not None
            and origin.boot_id == peer.boot_id
            and not peer.window.fresh(origin.boot_id, seal.counter)
        ):
            return self._refuse("replay")
        if src != peer.address and not proof and peer.proven:
            # A robot moves only to where it answers a challenge: a datagram sent again
            # from elsewhere must not move it (nor bring a dead one back there).
            self._challenge(peer, src, now)
            return self._refuse("other-address")
        if origin.boot_id != peer.boot_id:
            if origin.boot_id < peer.boot_id and not proof:
                # An earlier life's datagram, late or replayed; or the robot lost its state
                # (and its clock): only its answer to a challenge tells.
                self._challenge(peer, src, now)
                return self._refuse("stale-boot")
            self._new_boot(peer, origin)
        elif peer.byebye_boot == origin.boot_id and not proof:
            # After a Byebye only a reply to our challenge brings that boot back (a Byebye
            # anyone could have sent must not lock a robot out).
            self._challenge(peer, src, now)
            return self._refuse("after-byebye")
        if seal is not None:
            peer.window.accept(origin.boot_id, seal.counter)
        if proof:
            peer.byebye_boot = None
        return peer, None

    def _refuse(self, reason: str) -> tuple[None, str]:
        self.counters.rejects[reason] += 1
        return None, reason

    def _admit(self, sealed: bool, now: float) -> str | None:
        """Make room for a new robot; the reason it cannot have any, else None."""
        if not sealed and self._unproven >= MAX_UNPROVEN:
            return "unproven-full"
        if len(self.peers) < MAX_PEERS:
            return None
        gone = [p for p in self.peers.values() if not p.reachable]
        if not gone:
            return "peers-full"
        oldest = min(gone, key=lambda p: p.last_heard)
        self._forget(oldest)
        if oldest.proven:
            self._removed.add(oldest.robot_id)
        return None

    def _forget(self, peer: Peer) -> None:
        del self.peers[peer.robot_id]
        if not peer.proven:
            self._unproven -= 1
        self._dirty.discard(peer.robot_id)
        for seq in [s for s, p in self._pings.items() if p.robot_id == peer.robot_id]:
            del self._pings[seq]

    def _is_proof(self, msg: wire.Message, origin: Origin, src: Addr) -> bool:
        """Whether `msg` answers one of our challenges, from where the challenge went."""
        if not isinstance(msg, Response) or msg.seq is None:
            return False
        ping = self._pings.get(msg.seq)
        return (
            ping is not None
            and ping.challenge
            and ping.robot_id == origin.robot_id
            and ping.addr == src
        )

    def _challenge(self, peer: Peer, addr: Addr, now: float) -> bool:
        """Ping `peer` at `addr` so that its answer settles a claim; False if none was sent.

        One at a time per robot, at most one a ping timeout, and CHALLENGE_RATE in all: a
        flood of claims costs a bounded trickle of pings.
        """
        if now < peer.challenged_at + self.config.ping_timeout:
            return True  # one is in flight (or was just answered)
        if not self._challenge_budget.take(now):
            self.counters.challenges_limited += 1
            if not peer.proven:  # try again as soon as the budget allows
                peer.next_ping = min(peer.next_ping, now + 1.0 / CHALLENGE_RATE)
            return False
        peer.challenged_at = now
        self.counters.challenges += 1
        self._ping(peer, now, addr=addr, challenge=True)
        return True

    def _address_proven(self, addr: Addr, now: float) -> bool:
        """Whether `addr` answered a ping of ours lately: it may get more than it sent."""
        t = self._answered.get(addr)
        return t is not None and now - t <= self.config.proven_for

    def _prune(self, now: float) -> None:
        horizon = now - self.config.proven_for
        for addr in [a for a, t in self._answered.items() if t < horizon]:
            del self._answered[addr]
        self._next_prune = now + self.config.proven_for

    def _plain_search_allowed(self, data: bytes) -> bool:
        """An unsigned plain SSDP search in a keyed fleet, which ssdp_interop may answer."""
        return self.ssdp_interop and data.startswith(b"M-SEARCH ") and b"X-SDFR-" not in data

    def _on_plain_search(self, msg: Discovery, src: Addr, now: float) -> None:
        """A plain SSDP client: a standard search response, read-only, rate-limited."""
        cfg = self.config
        if not self.ssdp_interop:
            self.counters.rejects["ssdp-interop-off"] += 1
            return
        if not self._plain_budget.take(now):
            self.counters.rejects["rate-limited"] += 1
            return
        self._send(Response(self._origin(), msg.st, self.location, cfg.max_age), src)

    def _on_own_id(
        self, msg: wire.Message, origin: Origin, src: Addr, seal: Sealed | None, now: float
    ) -> None:
        """A datagram with our robot id: our own echo, a replay, or a second daemon."""
        if isinstance(msg, Response) and msg.seq is not None:
            ping = self._pings.pop(msg.seq, None)
            if ping is not None and ping.robot_id == origin.robot_id and ping.addr == src:
                self._conflict(src, origin, now)  # it answered: a live second daemon
                return
        if origin.boot_id == self.boot_id and src[0] == self._own_host():
            self.counters.rejects["own"] += 1  # our own datagram, come back
            return
        if seal is not None and origin.boot_id < self.boot_id:
            # An earlier life of ours replayed, or a second daemon started before us: a
            # challenge tells, since only a live daemon answers one.
            self.counters.rejects["own"] += 1
            if now >= self._own_challenge_at + self.config.ping_timeout:
                self._own_challenge_at = now
                seq = self._next_seq()
                self._pings[seq] = _Ping(origin.robot_id, now, src, challenge=True)
                self._send(Discovery(self._origin(), self._me(), 0, seq=seq, multicast=False), src)
            return
        self._conflict(src, origin, now)
        if isinstance(msg, Discovery) and msg.seq is not None:
            # Let the other daemon find us out too.
            self._send(Response(self._origin(), msg.st, "", 0, msg.seq), src)

    def _conflict(self, src: Addr, origin: Origin, now: float) -> None:
        self.counters.rejects["own-id"] += 1
        c = self.conflict
        if c is None:
            self.conflict = Conflict(src[0], origin.boot_id, now)
        else:
            c.address, c.boot_id, c.last_seen, c.count = src[0], origin.boot_id, now, c.count + 1

    def _own_host(self) -> str | None:
        try:
            return urlsplit(self.location).hostname
        except ValueError:
            return None

    # -- message handlers ------------------------------------------------------------------

    def _targets(self) -> set[str]:
        cfg = self.config
        return {"ssdp:all", wire.DEVICE_TYPE, wire.fleet_target(cfg.fleet), self._me()}

    def _me(self) -> str:
        return f"uuid:{self.config.robot_id}"

    def _on_discovery(
        self, msg: Discovery, peer: Peer | None, src: Addr, now: float, *, answer_ping: bool
    ) -> None:
        cfg = self.config
        if peer is not None:
            self._heard(peer, msg.origin, src, now, None, False)
        if msg.seq is not None and answer_ping:
            # A ping (anyone's: a robot whose claims we doubt must still be able to prove us):
            # the compact reply, smaller than the ping, carrying our own ping to that peer
            # when it would be due within half a ping interval.
            ride = None
            if (
                peer is not None
                and peer.reachable
                and peer.proven
                and peer.address == src
                and peer.next_ping - now <= cfg.ping_interval / 2
                and not any(p.robot_id == peer.robot_id for p in self._pings.values())
            ):
                ride = self._new_ping(peer, now, src)
            self._send(Response(self._origin(), msg.st, "", 0, msg.seq, ride), src)
        if peer is None:
            return
        if msg.want == WANT_ALL or (msg.want is not None and msg.want_version != self.version):
            if msg.multicast:
                if len(self._reply_to) < MAX_REPLY_TO:
                    self._reply_to[src] = peer.robot_id
                delay = self.rng.uniform(0, min(float(msg.mx), cfg.reply_delay_max))
                self._reply_at = min(self._reply_at, now + delay)
            else:
                self._serve(peer, src, None, now)
        elif isinstance(msg.want, tuple):
            self._serve(peer, src, msg.want, now)
        if peer.robot_id in self.peers:
            # A searcher that just started announces its set right after searching.
            self._want_current(peer, now, soon=True)

    def _serve(self, peer: Peer, dst: Addr, only: tuple[int, ...] | None, now: float) -> None:
        """Send parts of our set to `dst` by unicast, once `dst` has proven a round trip."""
        if not self._address_proven(dst, now):
            peer.deferred = (dst, only)
            self._challenge(peer, dst, now)
            return
        parts = self._update_parts()
        wanted = len(parts) if only is None else sum(1 for i in only if i < len(parts))
        # Per address, at most FETCH_SETS_PER_S whole sets a second.
        if not parts or not self._fetch_budget.take(
            dst[0], now, wanted / (FETCH_SETS_PER_S * len(parts))
        ):
            self.counters.rejects["fetch-limited"] += 1
            return
        self._send_update_parts(dst, now, only=only)

    def _on_byebye(self, peer: Peer) -> None:
        if not peer.proven:
            self._forget(peer)
            return
        peer.byebye_boot = peer.boot_id
        if peer.reachable:
            peer.reachable = False
            peer.next_ping = math.inf
        peer.fetch = None
        self._dirty.add(peer.robot_id)

    def _on_update(self, peer: Peer, msg: Update, now: float) -> None:
        o = msg.origin
        if (o.boot_id, o.version, o.digest) != (peer.boot_id, peer.version, peer.digest):
            return  # an older set than the one announced since; the newer will come
        if peer.current:
            return  # a duplicate, or parts of a set we completed already
        if msg.base is not None:
            self._apply_delta(peer, msg)
            return
        f = peer.fetch
        if f is None or (f.boot_id, f.version, f.digest) != (o.boot_id, o.version, o.digest):
            f = peer.fetch = _Fetch(
                o.boot_id, o.version, o.digest, retry_at=now + self.config.fetch_wait
            )
        if f.parts == 0:
            f.parts = msg.parts
        elif f.parts != msg.parts:
            self.counters.rejects["inconsistent-parts"] += 1
            peer.fetch = None
            return
        share = max(UNPROVEN_PARTS_MIN, UNPROVEN_PARTS // max(1, self._unproven))
        if not peer.proven and len(f.got) >= share and msg.part not in f.got:
            self.counters.rejects["unproven-parts"] += 1
            return
        f.got[msg.part] = msg.services
        if f.missing():
            # More parts are normally right behind this one; ask only if they do not come.
            f.retry_at = max(f.retry_at, now + self.config.fetch_wait)
            return
        services = tuple(s for i in range(f.parts) for s in f.got[i])
        peer.fetch = None
        if service_digest(services) != o.digest:
            self.counters.rejects["bad-digest"] += 1
            return
        peer.services = services
        peer.held = (o.boot_id, o.version, o.digest)
        self._dirty.add(peer.robot_id)

    def _apply_delta(self, peer: Peer, msg: Update) -> None:
        """Turn the set we hold into the announced one; without its base, fetch it whole."""
        o = msg.origin
        if peer.held is None or peer.held[:2] != (o.boot_id, msg.base):
            return
        changed = {s.id: s for s in msg.services}
        gone = set(msg.removed)
        services = [changed.pop(s.id, s) for s in peer.services if s.id not in gone]
        services.extend(changed.values())
        result = tuple(services)
        if service_digest(result) != o.digest:
            self.counters.rejects["bad-digest"] += 1
            return
        peer.services = result
        peer.held = (o.boot_id, o.version, o.digest)
        peer.fetch = None
        self._dirty.add(peer.robot_id)

    def _on_response(self, peer: Peer, msg: Response, src: Addr, now: float) -> None:
        if msg.seq is None:
            return
        if msg.ping is not None:  # the peer's ping, riding on its reply to ours
            self._send(Response(self._origin(), self._me(), "", 0, msg.ping), src)
        pending = self._pings.pop(msg.seq, None)
        if pending is None or pending.robot_id != peer.robot_id or pending.addr != src:
            return
        sample = now - pending.sent
        peer.rtt = sample if peer.rtt is None else 0.8 * peer.rtt + 0.2 * sample
        self._answered[src] = now
        self._settle_ping(peer, ok=True)
        if not peer.proven:
            peer.proven = True
            self._unproven -= 1
            peer.next_ping = now + self.rng.uniform(0.1, 1.0) * self.config.ping_interval
            self._dirty.add(peer.robot_id)
        if peer.deferred is not None:
            dst, only = peer.deferred
            peer.deferred = None
            if dst == src:
                self._serve(peer, dst, only, now)
        if peer.fetch is not None and peer.fetch.retry_at == math.inf:
            peer.fetch.retry_at = now  # held back while it was unproven

    # -- peer bookkeeping ------------------------------------------------------------------

    def _heard(
        self,
        peer: Peer,
        origin: Origin | None,
        src: Addr,
        now: float,
        location: str | None,
        proof: bool,
    ) -> None:
        """Record a sign of life from a peer `_gate` let through."""
        if origin is not None:
            if proof:
                # The answer to a challenge: what the robot says of itself now.
                if (origin.version, origin.digest) != (peer.version, peer.digest):
                    peer.version, peer.digest = origin.version, origin.digest
                    self._dirty.add(peer.robot_id)
            elif origin.version > peer.version or (
                origin.version == peer.version and origin.digest != peer.digest
            ):
                peer.version, peer.digest = origin.version, origin.digest
            elif origin.version < peer.version:
                # Reordered (an older announcement), or the version we hold was never the
                # robot's: it still shows the robot is there, and its answer will tell.
                self._challenge(peer, src, now)
        peer.last_heard = now
        if peer.address != src:
            peer.address = src
            self._dirty.add(peer.robot_id)
        if location and location != peer.location:
            peer.location = location
            self._dirty.add(peer.robot_id)
        if not peer.reachable:
            peer.reachable = True
            self.arrivals += 1
            # The ping window is kept: the pings lost while the peer was away are part of its
            # link's record, and the window slides them out as new pings settle.
            if peer.proven:
                peer.next_ping = now + self.rng.uniform(0.1, 1.0) * self.config.ping_interval
            self._dirty.add(peer.robot_id)

    def _new_boot(self, peer: Peer, origin: Origin) -> None:
        """The peer restarted: its old service set goes, never merged with the new one."""
        peer.boot_id, peer.version, peer.digest = origin.boot_id, origin.version, origin.digest
        peer.held = None
        peer.services = ()
        peer.fetch = None
        peer.byebye_boot = None
        self._dirty.add(peer.robot_id)

    def _want_current(self, peer: Peer, now: float, *, soon: bool) -> None:
        """Make sure we will come to hold the set the peer announced."""
        if peer.current:
            return
        if peer.held is None and peer.digest == self._empty_digest():
            # An empty set needs no fetch.
            peer.services = ()
            peer.held = (peer.boot_id, peer.version, peer.digest)
            peer.fetch = None
            self._dirty.add(peer.robot_id)
            return
        f = peer.fetch
        if f is not None and (f.boot_id, f.version, f.digest) == (
            peer.boot_id,
            peer.version,
            peer.digest,
        ):
            return  # already fetching this one
        peer.fetch = _Fetch(peer.boot_id, peer.version, peer.digest)
        if soon:
            peer.fetch.retry_at = now + self.config.fetch_wait
        else:
            self._request_fetch(peer, now)

    def _request_fetch(self, peer: Peer, now: float) -> None:
        """Ask the peer, by unicast, for the parts of its set we lack."""
        f = peer.fetch
        if f is None:
            return
        if not peer.proven:
            f.retry_at = math.inf  # asked once it answers its challenge
            return
        want: wire.Want = f.missing() if f.parts else WANT_ALL
        self._send(
            Discovery(
                self._origin(),
                f"uuid:{peer.robot_id}",
                0,
                want=want,
                want_version=f.version,
                multicast=False,
            ),
            peer.address,
        )
        f.backoff = min(self.config.beacon_interval, max(2 * f.backoff, self.config.fetch_wait * 2))
        f.retry_at = now + f.backoff * self.rng.uniform(0.8, 1.2)

    def _ping(
        self, peer: Peer, now: float, *, addr: Addr | None = None, challenge: bool = False
    ) -> None:
        dst = peer.address if addr is None else addr
        seq = self._new_ping(peer, now, dst, challenge=challenge)
        self._send(
            Discovery(self._origin(), f"uuid:{peer.robot_id}", 0, seq=seq, multicast=False), dst
        )

    def _next_seq(self) -> int:
        self._ping_seq = (self._ping_seq + 1) & 0x7FFFFFFF
        return self._ping_seq

    def _new_ping(self, peer: Peer, now: float, dst: Addr, *, challenge: bool = False) -> int:
        """A ping to `peer` at `dst` sent now (its sequence number); the next is a period away."""
        seq = self._next_seq()
        self._pings[seq] = _Ping(peer.robot_id, now, dst, challenge)
        jitter = self.rng.uniform(1 - self.config.jitter, 1.0)
        if peer.proven:
            peer.next_ping = now + self.config.ping_interval * jitter
        else:  # challenged again after a ping timeout until it answers (a lossy link may
            # lose a few round trips in a row; CHALLENGE_RATE bounds what fakes can cost)
            peer.next_ping = now + self.config.ping_timeout * (2 - jitter)
        return seq

    def _settle_ping(self, peer: Peer, *, ok: bool) -> None:
        before = peer.indicator
        peer.pings.append(ok)
        while len(peer.pings) > self.config.ping_window:
            peer.pings.popleft()
        if peer.indicator != before:
            self._dirty.add(peer.robot_id)

    # -- sending ---------------------------------------------------------------------------

    def _origin(self) -> Origin:
        return Origin(
            self.config.fleet, self.config.robot_id, self.boot_id, self.version, self.digest
        )

    def _beacon_period(self) -> float:
        return self.config.beacon_interval * self.rng.uniform(1 - self.config.jitter, 1.0)

    def _search(self, now: float) -> None:
        cfg = self.config
        self._send(
            Discovery(self._origin(), wire.fleet_target(cfg.fleet), cfg.mx, want=WANT_ALL), None
        )

    def _flush_replies(self, now: float) -> None:
        """Answer the searches gathered during the reply delay: one multicast serves many.

        A lone searcher gets the set by unicast (once its address has answered a ping of
        ours); several by multicast, at most once every MCAST_SET_GAP (a multicast is aimed
        at nobody, and a flood of searches costs one set a gap).
        """
        targets = self._reply_to
        if len(targets) == 1:
            ((dst, robot_id),) = targets.items()
            self._reply_to, self._reply_at = {}, math.inf
            peer = self.peers.get(robot_id)
            if peer is not None:
                self._serve(peer, dst, None, now)
            return
        if now < self._last_set_multicast + MCAST_SET_GAP:
            self._reply_at = self._last_set_multicast + MCAST_SET_GAP
            return
        self._reply_to, self._reply_at = {}, math.inf
        if targets:
            self._send_update_parts(None, now)

    def _update_parts(self) -> list[bytes]:
        key = (self.boot_id, self.version, self.digest, self.location)
        if self._parts_cache is None or self._parts_cache[0] != key:
            try:
                parts = wire.encode_update_parts(
                    self._origin(),
                    self.location,
                    self.config.max_age,
                    self.services,
                    group=self.config.group,
                    port=self.config.port,
                )
                self.announce_error = None
            except ValueError as exc:
                # Nothing a peer could assemble: announce nothing (the beacons still go out)
                # and say why, rather than stop.  The API refuses sets this large.
                parts = []
                self.announce_error = f"cannot announce the service set: {exc}"
            self._parts_cache = (key, parts)
        return self._parts_cache[1]

    def _announce_change(self, now: float) -> None:
        """Multicast what changed since the last announcement: a delta when it is smaller."""
        prev = self._announced
        if prev is None or prev[0] >= self.version:
            self._send_update_parts(None, now)
            return
        old = {s.id: s for s in prev[1]}
        new_ids = {s.id for s in self.services}
        added = tuple(s for s in self.services if old.get(s.id) != s)
        removed = tuple(sid for sid in old if sid not in new_ids)
        delta = Update(
            self._origin(),
            self.location,
            self.config.max_age,
            0,
            1,
            added,
            base=prev[0],
            removed=removed,
        )
        try:
            data = wire.encode(delta, group=self.config.group, port=self.config.port)
        except ValueError:  # too large for one datagram: the whole set, in parts
            self._send_update_parts(None, now)
            return
        if len(data) >= sum(map(len, self._update_parts())):
            self._send_update_parts(None, now)
            return
        self._announced = (self.version, self.services)
        self._emit(data, None, "update")

    def _send_update_parts(
        self, dst: Addr | None, now: float, only: Sequence[int] | None = None
    ) -> None:
        if dst is None:
            # A multicast set answers every pending search too.
            self._reply_to.clear()
            self._reply_at = math.inf
            self._update_at = math.inf
            self._announced = (self.version, self.services)
            self._last_set_multicast = now
        parts = self._update_parts()
        for i, data in enumerate(parts):
            if only is None or i in only:
                self._emit(data, dst, "update")

    def _send(self, msg: wire.Message, dst: Addr | None) -> None:
        if isinstance(msg, Discovery) and not msg.multicast and dst is not None:
            # A unicast search names the robot it is sent to in HOST.
            data = wire.encode(msg, group=dst[0], port=dst[1])
        else:
            data = wire.encode(msg, group=self.config.group, port=self.config.port)
        kind = type(msg).__name__.lower()
        self._emit(data, dst, kind)

    def _emit(self, data: bytes, dst: Addr | None, kind: str) -> None:
        ring = self.keyring
        if ring.signs and ring.primary is not None:
            self._sent_seals += 1
            data = auth.seal(data, ring.keys[ring.primary], self._sent_seals)
        self.counters.datagrams_out[kind] += 1
        self.counters.bytes_out += len(data)
        self._out.append((data, dst))

    _EMPTY = service_digest(())

    def _empty_digest(self) -> str:
        return self._EMPTY
