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
"""

from __future__ import annotations

import math
import random
from collections import Counter, deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from sdfr import wire
from sdfr.model import Service, service_digest
from sdfr.wire import WANT_ALL, Alive, Byebye, Discovery, Origin, Reject, Response, Update

#: A unicast destination; `None` in an outgoing datagram means the multicast group.
Addr = tuple[str, int]
Outgoing = tuple[bytes, Addr | None]

MESSAGE_TYPES = ("discovery", "response", "update", "alive", "byebye")


@dataclass(frozen=True, slots=True)
class CoreConfig:
    """Protocol timing; the defaults are the product's (the paper's 10 s beacon)."""

    fleet: int
    robot_id: str
    beacon_interval: float = 10.0
    miss_limit: int = 3
    ping_interval: float = 10.0
    ping_window: int = 20
    reply_delay_max: float = 0.5
    mx: int = 1
    jitter: float = 0.1
    update_coalesce: float = 0.02
    fetch_wait: float = 0.25
    group: str = wire.DEFAULT_GROUP
    port: int = wire.DEFAULT_PORT

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
    #: (boot, version, digest) the `services` below belong to; None when we hold no set.
    held: tuple[int, int, str] | None = None
    services: tuple[Service, ...] = ()
    byebye_boot: int | None = None
    pings: deque[bool] = field(default_factory=deque)
    rtt: float | None = None
    next_ping: float = math.inf
    fetch: _Fetch | None = None

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


@dataclass(frozen=True, slots=True)
class PeerView:
    """A peer as the history map stores it (core-clock times)."""

    robot_id: str
    address: str
    location: str
    boot_id: int
    version: int
    digest: str
    reachable: bool
    first_seen: float
    last_heard: float
    indicator: float | None
    rtt: float | None
    pings: int
    services: tuple[Service, ...]


@dataclass(slots=True)
class Counters:
    datagrams_in: Counter[str] = field(default_factory=Counter)
    datagrams_out: Counter[str] = field(default_factory=Counter)
    bytes_in: int = 0
    bytes_out: int = 0
    rejects: Counter[str] = field(default_factory=Counter)


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
    ) -> None:
        self.config = config
        self.boot_id = boot_id
        self.location = location
        self.rng = rng
        self.version = version
        self.services: tuple[Service, ...] = tuple(services)
        self.digest = service_digest(self.services)
        self.peers: dict[str, Peer] = {}
        self.counters = Counters()
        self._out: list[Outgoing] = []
        self._dirty: set[str] = set()
        #: Address -> when a ping to it was last answered (a round trip proven).
        self._answered: dict[Addr, float] = {}
        #: How many times a peer became reachable (a merge or an arrival shows here).
        self.arrivals = 0
        self._started = False
        self._stopped = False
        self._next_beacon = math.inf
        self._discovery_repeat = math.inf
        self._update_at = math.inf
        self._reply_at = math.inf
        self._reply_to: set[Addr] = set()
        self._pings: dict[int, tuple[str, float]] = {}
        self._ping_seq = rng.randrange(1 << 30)
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
        self._send_update_parts(None)
        # A second search covers a lost first one; beacons cover the rest.
        self._discovery_repeat = now + self.config.reply_delay_max + self.rng.uniform(0.2, 0.5)
        self._next_beacon = now + self._beacon_period()

    def stop(self, now: float) -> None:
        """Say goodbye; nothing is sent after this."""
        if self._started and not self._stopped:
            self._send(Byebye(self._origin()), None)
        self._stopped = True

    # -- inputs ----------------------------------------------------------------------------

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

    def restore(self, views: Iterable[PeerView]) -> None:
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
                last_heard=v.last_heard,
                boot_id=v.boot_id,
                version=v.version,
                digest=v.digest,
                reachable=False,
                held=held,
                services=v.services if held else (),
                rtt=v.rtt,
            )

    def receive(self, data: bytes, src: Addr, now: float) -> None:
        """A datagram arrived from `src`."""
        self.counters.bytes_in += len(data)
        msg = wire.decode(data, fleet=self.config.fleet)
        if isinstance(msg, Reject):
            self.counters.rejects[msg.reason] += 1
            return
        if self._stopped:
            return
        if isinstance(msg, Discovery):
            self.counters.datagrams_in["discovery"] += 1
            self._on_discovery(msg, src, now)
            return
        origin = msg.origin
        if isinstance(msg, Response):
            kind = "response"
        elif isinstance(msg, Update):
            kind = "update"
        elif isinstance(msg, Alive):
            kind = "alive"
        else:
            kind = "byebye"
        self.counters.datagrams_in[kind] += 1
        if origin.robot_id == self.config.robot_id:
            self.counters.rejects["own"] += 1
            return
        if isinstance(msg, Byebye):
            self._on_byebye(origin, now)
            return
        peer = self._heard(origin, src, now, getattr(msg, "location", None))
        if peer is None:
            return
        soon = False
        if isinstance(msg, Update):
            # More parts of a whole set are normally right behind this one; a delta we
            # could not apply will not be followed by anything that helps.
            soon = msg.base is None
            self._on_update(peer, msg, now)
        elif isinstance(msg, Response):
            self._on_response(peer, msg, now)
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
            self._announce_change()
        if now >= self._reply_at:
            self._flush_replies()
        if now >= self._next_beacon:
            self._send(Alive(self._origin(), self.location, cfg.max_age), None)
            self._next_beacon = now + self._beacon_period()
        expired = [seq for seq, (_, sent) in self._pings.items() if now >= sent + cfg.ping_timeout]
        for seq in expired:
            robot_id, _ = self._pings.pop(seq)
            peer = self.peers.get(robot_id)
            if peer is not None:
                self._settle_ping(peer, ok=False)
        for peer in self.peers.values():
            if peer.reachable and now >= peer.last_heard + cfg.dead_after:
                peer.reachable = False
                peer.next_ping = math.inf
                peer.fetch = None
                self._dirty.add(peer.robot_id)
                continue
            if peer.reachable and now >= peer.next_ping:
                self._ping(peer, now)
            if peer.fetch is not None and now >= peer.fetch.retry_at:
                self._request_fetch(peer, now)

    def next_deadline(self) -> float | None:
        """When `handle_timer` must run next (None: only an input can change anything)."""
        if not self._started or self._stopped:
            return None
        cfg = self.config
        t = min(self._next_beacon, self._discovery_repeat, self._update_at, self._reply_at)
        for _, sent in self._pings.values():
            t = min(t, sent + cfg.ping_timeout)
        for peer in self.peers.values():
            if peer.reachable:
                t = min(t, peer.last_heard + cfg.dead_after, peer.next_ping)
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
        if t is None:
            return False
        if now - t > 2 * self.config.ping_interval:
            del self._answered[addr]
            return False
        return True

    @property
    def has_dirty(self) -> bool:
        return bool(self._dirty)

    def take_dirty(self) -> list[PeerView]:
        """Peers whose stored view changed since the last call."""
        views = [self.view(self.peers[r]) for r in sorted(self._dirty) if r in self.peers]
        self._dirty.clear()
        return views

    def view(self, peer: Peer) -> PeerView:
        return PeerView(
            robot_id=peer.robot_id,
            address=peer.address[0],
            location=peer.location,
            boot_id=peer.boot_id,
            version=peer.version,
            digest=peer.digest,
            reachable=peer.reachable,
            first_seen=peer.first_seen,
            last_heard=peer.last_heard,
            indicator=peer.indicator,
            rtt=peer.rtt,
            pings=len(peer.pings),
            services=peer.services,
        )

    def reachable(self) -> list[str]:
        return sorted(r for r, p in self.peers.items() if p.reachable)

    # -- message handlers ------------------------------------------------------------------

    def _on_discovery(self, msg: Discovery, src: Addr, now: float) -> None:
        cfg = self.config
        me = f"uuid:{cfg.robot_id}"
        targets = {"ssdp:all", wire.DEVICE_TYPE, wire.fleet_target(cfg.fleet), me}
        if msg.st not in targets:
            self.counters.rejects["other-target"] += 1
            return
        if msg.origin is None:
            # A plain SSDP client: answer with a standard search response.
            self._send(Response(self._origin(), msg.st, self.location, cfg.max_age), src)
            return
        if msg.origin.robot_id == cfg.robot_id:
            self.counters.rejects["own"] += 1
            return
        peer = self._heard(msg.origin, src, now, None)
        if msg.seq is not None:
            # A ping from a peer: the compact reply (no SSDP lines it does not need), carrying
            # our own ping to that peer when it would be due within half a ping interval.
            ping = None
            if (
                peer is not None
                and peer.reachable
                and peer.next_ping - now <= cfg.ping_interval / 2
                and not any(p[0] == peer.robot_id for p in self._pings.values())
            ):
                ping = self._new_ping(peer, now)
            self._send(Response(self._origin(), msg.st, "", 0, msg.seq, ping), src)
        if msg.want == WANT_ALL or (msg.want is not None and msg.want_version != self.version):
            if msg.multicast:
                delay = self.rng.uniform(0, min(float(msg.mx), cfg.reply_delay_max))
                self._reply_to.add(src)
                self._reply_at = min(self._reply_at, now + delay)
            else:
                self._send_update_parts(src)
        elif isinstance(msg.want, tuple):
            self._send_update_parts(src, only=msg.want)
        if peer is not None:
            # A searcher that just started announces its set right after searching.
            self._want_current(peer, now, soon=True)

    def _on_byebye(self, origin: Origin, now: float) -> None:
        peer = self.peers.get(origin.robot_id)
        if peer is None or origin.boot_id < peer.boot_id:
            return
        if origin.boot_id > peer.boot_id:
            self._new_boot(peer, origin)
        peer.byebye_boot = origin.boot_id
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

    def _on_response(self, peer: Peer, msg: Response, now: float) -> None:
        if msg.seq is None:
            return
        if msg.ping is not None:  # the peer's ping, riding on its reply to ours
            me = f"uuid:{self.config.robot_id}"
            self._send(Response(self._origin(), me, "", 0, msg.ping), peer.address)
        pending = self._pings.pop(msg.seq, None)
        if pending is None or pending[0] != peer.robot_id:
            return
        sample = now - pending[1]
        peer.rtt = sample if peer.rtt is None else 0.8 * peer.rtt + 0.2 * sample
        self._answered[peer.address] = now
        self._settle_ping(peer, ok=True)

    # -- peer bookkeeping ------------------------------------------------------------------

    def _heard(self, origin: Origin, src: Addr, now: float, location: str | None) -> Peer | None:
        """Record a sign of life; returns None when the message is stale and must be ignored."""
        peer = self.peers.get(origin.robot_id)
        if peer is None:
            peer = Peer(
                robot_id=origin.robot_id,
                address=src,
                location=location or "",
                first_seen=now,
                last_heard=now,
                boot_id=origin.boot_id,
                version=origin.version,
                digest=origin.digest,
            )
            self.peers[origin.robot_id] = peer
        elif origin.boot_id < peer.boot_id:
            # A datagram from an earlier life arriving late, unless that robot lost its
            # state (boot ids restart) and has been silent long enough to be a new life.
            if peer.reachable or now < peer.last_heard + self.config.dead_after:
                self.counters.rejects["stale-boot"] += 1
                return None
            self._new_boot(peer, origin)
        elif origin.boot_id > peer.boot_id:
            self._new_boot(peer, origin)
        elif peer.byebye_boot == origin.boot_id:
            self.counters.rejects["after-byebye"] += 1
            return None
        elif origin.version > peer.version or (
            origin.version == peer.version and origin.digest != peer.digest
        ):
            peer.version, peer.digest = origin.version, origin.digest
        elif origin.version < peer.version:
            # Reordered: an older announcement. It still proves the robot is there.
            pass
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
            peer.next_ping = now + self.rng.uniform(0.1, 1.0) * self.config.ping_interval
            self._dirty.add(peer.robot_id)
        return peer

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

    def _ping(self, peer: Peer, now: float) -> None:
        seq = self._new_ping(peer, now)
        self._send(
            Discovery(self._origin(), f"uuid:{peer.robot_id}", 0, seq=seq, multicast=False),
            peer.address,
        )

    def _new_ping(self, peer: Peer, now: float) -> int:
        """A ping to `peer` sent now (its sequence number); the next one is a period away."""
        self._ping_seq = (self._ping_seq + 1) & 0x7FFFFFFF
        self._pings[self._ping_seq] = (peer.robot_id, now)
        jitter = self.rng.uniform(1 - self.config.jitter, 1.0)
        peer.next_ping = now + self.config.ping_interval * jitter
        return self._ping_seq

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

    def _flush_replies(self) -> None:
        """Answer the searches gathered during the reply delay: one multicast serves many."""
        targets, self._reply_to = self._reply_to, set()
        self._reply_at = math.inf
        if len(targets) == 1:
            self._send_update_parts(next(iter(targets)))
        elif targets:
            self._send_update_parts(None)

    def _update_parts(self) -> list[bytes]:
        key = (self.boot_id, self.version, self.digest, self.location)
        if self._parts_cache is None or self._parts_cache[0] != key:
            parts = wire.encode_update_parts(
                self._origin(),
                self.location,
                self.config.max_age,
                self.services,
                group=self.config.group,
                port=self.config.port,
            )
            self._parts_cache = (key, parts)
        return self._parts_cache[1]

    def _announce_change(self) -> None:
        """Multicast what changed since the last announcement: a delta when it is smaller."""
        prev = self._announced
        if prev is None or prev[0] >= self.version:
            self._send_update_parts(None)
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
            self._send_update_parts(None)
            return
        if len(data) >= sum(map(len, self._update_parts())):
            self._send_update_parts(None)
            return
        self._announced = (self.version, self.services)
        self._reply_to.clear()
        self._reply_at = math.inf
        self._emit(data, None, "update")

    def _send_update_parts(self, dst: Addr | None, only: Sequence[int] | None = None) -> None:
        if dst is None:
            # A multicast set answers every pending search too.
            self._reply_to.clear()
            self._reply_at = math.inf
            self._update_at = math.inf
            self._announced = (self.version, self.services)
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
        self.counters.datagrams_out[kind] += 1
        self.counters.bytes_out += len(data)
        self._out.append((data, dst))

    _EMPTY = service_digest(())

    def _empty_digest(self) -> str:
        return self._EMPTY
