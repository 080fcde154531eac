"""The protocol core's state, its peer bookkeeping (pings, fetches) and what it sends.

`Core` builds on it: what arrives, and whom to trust.
"""

from __future__ import annotations

import ipaddress
import math
import random
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import replace

from sdfr import auth, wire
from sdfr.auth import OPEN, Keyring
from sdfr.limits import ByteCredit, KeyedBuckets, TokenBucket
from sdfr.model import Service, service_digest
from sdfr.protocol.config import (
    ADDR_CHALLENGE_BURST,
    ADDR_CHALLENGE_RATE,
    CHALLENGE_BURST,
    CHALLENGE_GAP,
    CHALLENGE_PAD,
    CHALLENGE_RATE,
    CREDIT_CAP,
    DELTA_STEPS,
    MAX_PINGS,
    MAX_SOURCES,
    PLAIN_BURST,
    PLAIN_RATE,
    PLAIN_SOURCE_BURST,
    PLAIN_SOURCE_RATE,
    REPAIR_MEMORY,
    SOURCE_BURST,
    SOURCE_RATE,
    Addr,
    CoreConfig,
    Outgoing,
    answers_beacon,
)
from sdfr.protocol.peers import Conflict, Counters, Peer, _Fetch, _GroupPing, _Ping
from sdfr.wire import MAX_SEQ, WANT_ALL, WIRE_COMPACT, WIRE_FULL, Alive, Discovery, Origin, Update

#: The header that pads a challenge (`CHALLENGE_PAD` bytes in all).
PAD_HEADER = b"X-SDFR-PAD: "
_PAD_FIXED = len(PAD_HEADER) + 2


class CoreState:
    """One robot's protocol state, and the sending side of it.

    `rng` draws the jitter and the pings' nonces: outside tests it must be unpredictable
    (sdfrd passes `random.SystemRandom()`), since a nonce an outsider can guess proves nothing.
    """

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
        self.subnet: ipaddress.IPv4Network | ipaddress.IPv6Network | None = None
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
        #: Pings in flight, by nonce (their sequence number).
        self._pings: dict[int, _Ping] = {}
        #: Which turn of peers our last beacon asked to answer (`answers_beacon`), and of how
        #: many turns.
        self._beacon_turn = 0
        self._turns = 1
        self._sent_seals = 0
        self._sources = KeyedBuckets(SOURCE_RATE, SOURCE_BURST, MAX_SOURCES)
        self._fetch_budget = KeyedBuckets(1.0, 1.0, MAX_SOURCES)
        self._challenge_budget = TokenBucket(CHALLENGE_RATE, CHALLENGE_BURST)
        self._addr_challenges = KeyedBuckets(ADDR_CHALLENGE_RATE, ADDR_CHALLENGE_BURST, MAX_SOURCES)
        self._plain_budget = TokenBucket(PLAIN_RATE, PLAIN_BURST)
        self._plain_sources = KeyedBuckets(PLAIN_SOURCE_RATE, PLAIN_SOURCE_BURST, MAX_SOURCES)
        #: Invitations to challenge us (`_invite`): one a beacon period.
        self._invites = TokenBucket(1.0 / config.beacon_interval, 1.0)
        #: What each address sent us and we did not spend on answers to it yet: all an address
        #: that has not proven a round trip may get from us (no amplification).
        self._credit = ByteCredit(CREDIT_CAP, MAX_SOURCES)
        #: Bytes of services held in sets not yet believed (`UNPROVEN_BYTES` in all).
        self._held_bytes = 0
        self._own_challenge_at = -math.inf
        #: The time of the input being handled (what `_emit` judges proofs against).
        self._now = 0.0
        self._parts_cache: tuple[tuple[int, int, str, str, bool], list[bytes]] | None = None
        #: The set every robot in range last heard by multicast, (version, services, digest):
        #: what everything we send names as ours and serves (a change not announced yet is
        #: not told of by a beacon or a ping, so nobody fetches a set that is about to come),
        #: and the base of the next delta.  None before `start`.
        self._announced: tuple[int, tuple[Service, ...], str] | None = None
        #: Sets announced lately, by version: a robot that missed a change is sent what
        #: changed since the set it holds.
        self._recent: OrderedDict[int, tuple[Service, ...]] = OrderedDict()
        self._last_change_sent = -math.inf
        self._dictionary_cache: tuple[int, bytes] | None = None
        #: The last multicast deltas' own steps, (base, version, body), oldest first, while
        #: each followed the one before: what the next delta carries when repairing.
        self._steps: list[tuple[int, int, bytes]] = []
        #: When a peer last asked for a catch-up (what changed since a set it holds).
        self._repair_asked = -math.inf
        #: Beacons sent as pings, by sequence number.
        self._group_pings: dict[int, _GroupPing] = {}
        #: Address -> the wire version of the peer there (what unicasts to it may be).
        self._wire_at: dict[Addr, int] = {}

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
        """Record a sign of life from a peer `_gate` let through: its datagram came from its
        proven address (or is its answer to a ping of ours, `proof`)."""
        if (
            origin is not None
            and not proof
            and (
                (origin.version, origin.digest) != (peer.version, peer.digest) or not peer.reachable
            )
        ):
            # A change of its set, or a robot whose last answer is too old to list it: only
            # its answer to a ping (fresh by construction) is believed.  (One that is not
            # listed may not list us either: the challenge pays for its own, `CHALLENGE_PAD`.)
            self._doubt(peer, src, now, pad=not peer.reachable)
        peer.last_heard = now
        if origin is not None and origin.wire != peer.wire:
            peer.wire = origin.wire
            if peer.reachable and self._by_beacon(peer):
                peer.next_ping = math.inf  # its beacon pings stand in for unicast ones now
        if origin is not None:
            self._wire_at[src] = origin.wire
        if location and location != peer.location:
            peer.location = location
            self._dirty.add(peer.robot_id)

    def _prove(self, peer: Peer, origin: Origin, src: Addr, now: float) -> None:
        """The peer answered a ping of ours from `src`: believe what it says of itself now."""
        if (
            origin.boot_id != peer.boot_id
            or origin.version < peer.version
            or (origin.version == peer.version and origin.digest != peer.digest)
        ):
            # A new boot, or a new life under a boot id used again (its state was lost, and
            # its versions start over): nothing of the set we hold is its set now.
            self._new_boot(peer, origin)
        elif (origin.version, origin.digest) != (peer.version, peer.digest):
            peer.version, peer.digest = origin.version, origin.digest
            self._dirty.add(peer.robot_id)
        peer.byebye_boot = None
        peer.answered_at = now
        # Answered: the next claim (a change right behind this one) may be asked about soon,
        # not a ping timeout later; CHALLENGE_GAP bounds what forged claims cost it.
        self._challenge_soon(peer, now)
        if not peer.proven:
            peer.proven = True
            if not peer.known:
                peer.known = True
                self._unproven -= 1
            self._dirty.add(peer.robot_id)
        if peer.address != src:
            peer.address = src
            self._dirty.add(peer.robot_id)
        if not peer.reachable:
            peer.reachable = True
            self.arrivals += 1
            # The ping window is kept: the pings lost while the peer was away are part of its
            # link's record, and the window slides them out as new pings settle.
            self._schedule_ping(peer, now)
            self._dirty.add(peer.robot_id)

    def _challenge_soon(self, peer: Peer, now: float) -> None:
        """Let `peer` be challenged again CHALLENGE_GAP after now, not a ping timeout after its
        last challenge."""
        peer.challenged_at = min(peer.challenged_at, now - self.config.ping_timeout + CHALLENGE_GAP)

    def _new_boot(self, peer: Peer, origin: Origin) -> None:
        """The peer restarted: its old service set goes, never merged with the new one."""
        peer.boot_id, peer.version, peer.digest = origin.boot_id, origin.version, origin.digest
        peer.held = None
        peer.services = ()
        peer.dictionary = None
        peer.byebye_boot = None
        peer.window.reset()
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
        held = peer.held_delta
        if held is not None:
            peer.held_delta = None
            o = held.origin
            if (o.boot_id, o.version, o.digest) == (peer.boot_id, peer.version, peer.digest):
                self._apply_delta(peer, held)
                if peer.current:
                    return
        f = peer.fetch
        if f is not None and (f.boot_id, f.version, f.digest) == (
            peer.boot_id,
            peer.version,
            peer.digest,
        ):
            if f.parts and not f.missing():
                self._complete(peer)  # held while the set was not believed
            return  # already fetching this one
        self._drop_fetch(peer)
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
        if f.parts and not f.missing():
            # Whole already (held while not believed): it is the peer's set iff it is the one
            # the peer's answers named.
            if (f.boot_id, f.version, f.digest) == (peer.boot_id, peer.version, peer.digest):
                self._complete(peer)
            else:
                f.retry_at = math.inf
            return
        want: wire.Want = f.missing() if f.parts else WANT_ALL
        have = None
        if not f.parts and peer.held is not None and peer.held[0] == f.boot_id:
            # What we hold of the same boot: the answer can be what changed since.
            have = peer.held[1] if peer.held[1] < f.version else None
        self._send(
            Discovery(
                self._origin(),
                f"uuid:{peer.robot_id}",
                0,
                want=want,
                want_version=f.version,
                multicast=False,
                have=have,
            ),
            peer.address,
            to=peer.robot_id,
        )
        f.backoff = min(self.config.beacon_interval, max(2 * f.backoff, self.config.fetch_wait * 2))
        f.retry_at = now + f.backoff * self.rng.uniform(0.8, 1.2)

    def _ping(
        self,
        peer: Peer,
        now: float,
        *,
        addr: Addr | None = None,
        challenge: bool = False,
        pad: bool = False,
    ) -> bool:
        """Ping `peer` (at `addr`); False if it could not go (see `_emit`).  `pad`: see
        CHALLENGE_PAD."""
        dst = peer.address if addr is None else addr
        if len(self._pings) >= MAX_PINGS:
            self.counters.challenges_limited += 1
            return False
        seq = self._new_ping(peer, now, dst, challenge=challenge)
        ping = Discovery(self._origin(), f"uuid:{peer.robot_id}", 0, seq=seq, multicast=False)
        # (In the form the robot reads, wherever it is: a robot met at a new address gets the
        # small ping, which its first datagram from there pays for.)
        compact = self.config.wire_compact and peer.wire >= WIRE_COMPACT
        extra = CHALLENGE_PAD if pad else 0
        if self._send(ping, dst, to=peer.robot_id, compact=compact, pad=extra):
            return True
        del self._pings[seq]
        return False

    def _nonce(self, turns: int = 1, turn: int = 0) -> int:
        """A fresh random 64-bit sequence number for a ping (its answer proves the round trip
        happened now), of the given turn (`answers_beacon`: its value modulo `turns`)."""
        seq = self.rng.getrandbits(64)
        if turns > 1:
            seq = seq - seq % turns + turn
            if seq > MAX_SEQ:
                seq -= turns
        return seq

    def _beacon_pings(self) -> bool:
        """Whether our beacons are also pings (to the peers that answer them, `_by_beacon`)."""
        return self.config.wire_compact and self.config.ping_interval >= self.config.beacon_interval

    def _by_beacon(self, peer: Peer) -> bool:
        """Whether `peer` is pinged by our beacons rather than by unicast: it speaks wire 2
        (so it answers them) and is proven.  One multicast pings the whole fleet, and a round
        trip costs one datagram each way instead of a unicast ping and its reply."""
        return self._beacon_pings() and peer.proven and peer.wire >= WIRE_COMPACT

    def _schedule_ping(self, peer: Peer, now: float) -> None:
        """The first ping to a proven peer that became reachable: a random part of a period
        away, or none by unicast when beacons ping it."""
        if self._by_beacon(peer):
            peer.next_ping = math.inf
        else:
            peer.next_ping = now + self.rng.uniform(0.1, 1.0) * self.config.ping_interval

    def _new_ping(self, peer: Peer, now: float, dst: Addr, *, challenge: bool = False) -> int:
        """A ping to `peer` at `dst` sent now (its sequence number); the next is a period away."""
        seq = self._nonce()
        self._pings[seq] = _Ping(peer.robot_id, now, dst, challenge)
        jitter = self.rng.uniform(1 - self.config.jitter, 1.0)
        if peer.proven and self._by_beacon(peer):
            peer.next_ping = math.inf
        elif peer.proven:
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

    def _advertised(self) -> tuple[int, tuple[Service, ...], str]:
        """The set we tell of: the last announced, or before `start` the local one."""
        if self._announced is None:
            return self.version, self.services, self.digest
        return self._announced

    def _announce(self, now: float) -> None:
        """The local set is announced now: from here on it is what we tell of."""
        self._announced = (self.version, self.services, self.digest)
        self._recent[self.version] = self.services
        self._recent.move_to_end(self.version)
        while len(self._recent) > max(1, self.config.delta_history):
            self._recent.popitem(last=False)
        self._last_change_sent = now
        self._update_at = math.inf
        self._steps = []  # a delta sent now puts its own step back (`_announce_change`)

    def _origin(self) -> Origin:
        version, _, digest = self._advertised()
        w = WIRE_COMPACT if self.config.wire_compact else WIRE_FULL
        return Origin(self.config.fleet, self.config.robot_id, self.boot_id, version, digest, w)

    def _compact_for(self, dst: Addr | None) -> bool:
        """Whether a datagram to `dst` (None: the multicast group) goes in the compact form:
        to one peer when it reads it; to the group while every robot in range (and every
        unproven one heard lately) reads it."""
        if not self.config.wire_compact:
            return False
        if dst is not None:
            return self._wire_at.get(dst, WIRE_FULL) >= WIRE_COMPACT
        return all(
            p.wire >= WIRE_COMPACT
            for p in self.peers.values()
            if p.reachable or not (p.proven or p.known)
        )

    def _beacon(self, now: float) -> None:
        """The beacon; with beacon pings, a ping to every peer that answers them too (or, in
        a fleet of more than `beacon_answers` such peers, to those whose turn it is)."""
        cfg = self.config
        compact = self._compact_for(None)
        seq, turns = None, 1
        if self._beacon_pings():
            pinged = {
                p.robot_id: p.address
                for p in self.peers.values()
                if p.reachable and self._by_beacon(p)
            }
            if compact and len(pinged) > cfg.beacon_answers:
                turns = min(wire.MAX_TURNS, -(-len(pinged) // max(1, cfg.beacon_answers)))
            self._turns = turns
            seq = self._nonce()
            targets = pinged
            for _ in range(turns if turns > 1 else 0):
                # The next turn in order that has peers in it, as the seq says.
                self._beacon_turn = (self._beacon_turn + 1) % turns
                seq = self._nonce(turns, self._beacon_turn)
                targets = {
                    rid: addr for rid, addr in pinged.items() if answers_beacon(rid, seq, turns)
                }
                if targets:
                    break
            if targets or self.peers:
                # (Expecting no answer, it still proves the peers out of reach that hear it and
                # answer: after a merge the first beacon heard on each side lists the other.)
                self._group_pings[seq] = _GroupPing(now, targets)
            else:
                seq, turns = None, 1
        if compact:  # peers know where we are: no LOCATION, no max-age
            self._send(Alive(self._origin(), "", 0, seq, turns), None, compact=True)
        else:
            self._send(Alive(self._origin(), self.location, cfg.max_age, seq), None, compact=False)

    def _beacon_period(self) -> float:
        return self.config.beacon_interval * self.rng.uniform(1 - self.config.jitter, 1.0)

    def _search(self, now: float) -> None:
        cfg = self.config
        search = Discovery(self._origin(), wire.fleet_target(cfg.fleet), cfg.mx, want=WANT_ALL)
        self._send(search, None, compact=False)  # a multicast search is always a full one

    def _flush_replies(self, now: float) -> None:
        """Answer the searches gathered during the reply delay: one multicast serves many.

        A lone searcher gets the set by unicast (once its address has answered a ping of
        ours); several by multicast, at most once every `mcast_set_gap` (a multicast is aimed
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
        gap = self.config.mcast_set_gap
        if now < self._last_set_multicast + gap:
            self._reply_at = self._last_set_multicast + gap
            return
        self._reply_to, self._reply_at = {}, math.inf
        if targets:
            self._send_update_parts(None, now)

    def _update_parts(self, compact: bool = False) -> list[bytes]:
        """The set we tell of (`_advertised`), in parts."""
        version, services, digest = self._advertised()
        key = (self.boot_id, version, digest, self.location, compact)
        if self._parts_cache is None or self._parts_cache[0] != key:
            try:
                parts = wire.encode_update_parts(
                    self._origin(),
                    self.location,
                    self.config.max_age,
                    services,
                    group=self.config.group,
                    port=self.config.port,
                    compact=compact,
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
        """Multicast what changed since the last announcement: a delta when it is smaller.

        While peers lately asked for catch-ups, the delta also carries the steps of the
        deltas just before it (`REPAIR_MEMORY`), so that a robot that missed them catches up
        from this one datagram rather than by asking."""
        prev = self._announced
        if prev is None or prev[0] >= self.version:
            self._send_update_parts(None, now)
            return
        history = self._steps
        chained = history if history and history[-1][1] == prev[0] else []
        steps = chained if now - self._repair_asked <= REPAIR_MEMORY else []
        self._announce(now)
        compact = self._compact_for(None)
        data = self._delta(prev[0], prev[1], compact, [(b, body) for b, _, body in steps])
        if data is None:  # too large for one datagram, or no smaller than the whole set
            self._send_update_parts(None, now)
            return
        if compact and DELTA_STEPS > 1:
            own = (prev[0], self.version, wire.last_step(data))
            self._steps = [*chained, own][1 - DELTA_STEPS :]
        self._emit(data, None, "update")

    def _delta(
        self,
        base: int,
        had: tuple[Service, ...],
        compact: bool,
        steps: Sequence[tuple[int, bytes]] = (),
    ) -> bytes | None:
        """The datagram turning set `base` (`had`) into the one we tell of; None when it would
        not fit one datagram, or carry every service of the set anyway (the whole set, which
        needs no base, is then no bigger).  A compact one carries `steps` before its own when
        they fit."""
        old = {s.id: s for s in had}
        _, services, _ = self._advertised()
        new_ids = {s.id for s in services}
        added = tuple(s for s in services if old.get(s.id) != s)
        if services and len(added) == len(services):
            return None
        removed = tuple(sid for sid in old if sid not in new_ids)
        location, max_age = ("", 0) if compact else (self.location, self.config.max_age)
        delta = Update(self._origin(), location, max_age, 0, 1, added, base=base, removed=removed)
        cfg = self.config
        # Compact: deflated against the base set, which every robot that can apply it holds.
        dictionary = self._dictionary(base, had) if compact else None
        for chain in (tuple(steps), ()) if compact and steps else ((),):
            try:
                return wire.encode(
                    replace(delta, steps=chain),
                    group=cfg.group,
                    port=cfg.port,
                    compact=compact,
                    dictionary=dictionary,
                )
            except ValueError:
                continue
        return None

    def _dictionary(self, version: int, services: tuple[Service, ...]) -> bytes:
        """`wire.delta_dictionary` of our set `version`, kept for the next delta from it."""
        if self._dictionary_cache is None or self._dictionary_cache[0] != version:
            self._dictionary_cache = (version, wire.delta_dictionary(services))
        return self._dictionary_cache[1]

    def _catch_up(self, have: int, compact: bool) -> bytes | None:
        """What changed since our set `have`, for a robot that holds it (None: we no longer
        know that set, or the whole set is as small)."""
        version, _, _ = self._advertised()
        had = self._recent.get(have)
        if had is None or have >= version:
            return None
        return self._delta(have, had, compact)

    def _send_update_parts(
        self,
        dst: Addr | None,
        now: float,
        only: Sequence[int] | None = None,
        to: str | None = None,
    ) -> None:
        if dst is None:
            # A multicast set answers every pending search too.
            self._reply_to.clear()
            self._reply_at = math.inf
            self._announce(now)
            self._last_set_multicast = now
        parts = self._update_parts(self._compact_for(dst))
        for i, data in enumerate(parts):
            if only is None or i in only:
                self._emit(data, dst, "update", to=to)

    def _send(
        self,
        msg: wire.Message,
        dst: Addr | None,
        *,
        compact: bool | None = None,
        to: str | None = None,
        answer: bool = False,
        pad: int = 0,
    ) -> bool:
        """Encode and send `msg` (to robot `to` at `dst`; see `_emit`): compact when
        `_compact_for(dst)` (or as told), `pad` bytes longer (`PAD_HEADER`)."""
        if compact is None:
            compact = self._compact_for(dst)
        if compact:
            data = wire.encode(msg, compact=True)
        elif isinstance(msg, Discovery) and not msg.multicast and dst is not None:
            # A unicast search names the robot it is sent to in HOST.
            data = wire.encode(msg, group=dst[0], port=dst[1])
        else:
            data = wire.encode(msg, group=self.config.group, port=self.config.port)
        if pad > 0:
            # (Before the blank line; every decoder passes over a header it does not know.)
            data = b"%s%s%s\r\n\r\n" % (data[:-2], PAD_HEADER, b"0" * max(0, pad - _PAD_FIXED))
        kind = type(msg).__name__.lower()
        return self._emit(data, dst, kind, to=to, answer=answer)

    def _emit(
        self,
        data: bytes,
        dst: Addr | None,
        kind: str,
        *,
        to: str | None = None,
        answer: bool = False,
    ) -> bool:
        """Send `data` to the group (`dst` None) or to robot `to` at `dst`, sealed for it when
        the fleet signs.  An address that has not proven a round trip gets no more bytes than
        it sent us (`_credit`): False, and nothing sent, when this would be more.  `answer`:
        the one standard answer to a plain SSDP search, which its own limits bound."""
        ring = self.keyring
        if ring.signs and ring.primary is not None:
            self._sent_seals += 1
            sender = self._own_host() or ""
            target = None if dst is None else to
            data = auth.seal(
                data, ring.keys[ring.primary], self._sent_seals, to=target, sender=sender
            )
        if (
            dst is not None
            and not answer
            and not self._address_proven(dst, self._now)
            and not self._credit.spend(dst[0], len(data))
        ):
            self.counters.rejects["amplification"] += 1
            return False
        self.counters.datagrams_out[kind] += 1
        self.counters.bytes_out += len(data)
        self._out.append((data, dst))
        return True

    _EMPTY = service_digest(())

    def _empty_digest(self) -> str:
        return self._EMPTY

    # -- what the trust layer above provides (`Core`) ---------------------------------------

    def _challenge(self, peer: Peer, addr: Addr, now: float, *, pad: bool = True) -> bool:
        raise NotImplementedError

    def _doubt(
        self, peer: Peer, src: Addr, now: float, *, pad: bool = True, urgent: bool = False
    ) -> None:
        raise NotImplementedError

    def _address_proven(self, addr: Addr, now: float) -> bool:
        raise NotImplementedError

    def _own_host(self) -> str | None:
        raise NotImplementedError

    def _complete(self, peer: Peer) -> None:
        raise NotImplementedError

    def _drop_fetch(self, peer: Peer) -> None:
        raise NotImplementedError

    def _apply_delta(self, peer: Peer, msg: Update) -> None:
        raise NotImplementedError

    def _serve(self, peer: Peer, dst: Addr, only: tuple[int, ...] | None, now: float) -> None:
        raise NotImplementedError
