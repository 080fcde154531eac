"""The protocol core's state: the peer table, pings in flight, the token buckets, the
counters, what is due when, and the few reads every part of the core shares.

`Core` builds on it; the parts (`sending`, `beacons`, `challenges`, `trust`, `updates`,
`plain`, `timers`) are functions that take it.
"""

from __future__ import annotations

import ipaddress
import math
import random
from collections import OrderedDict
from collections.abc import Sequence
from urllib.parse import urlsplit

from sdfr.protocol import auth
from sdfr.protocol.auth import OPEN, Keyring
from sdfr.protocol.config import (
    ADDR_CHALLENGE_BURST,
    ADDR_CHALLENGE_RATE,
    CHALLENGE_BURST,
    CHALLENGE_RATE,
    CREDIT_CAP,
    MAX_SOURCES,
    PLAIN_BURST,
    PLAIN_RATE,
    PLAIN_SOURCE_BURST,
    PLAIN_SOURCE_RATE,
    SOURCE_BURST,
    SOURCE_RATE,
    Addr,
    CoreConfig,
    Outgoing,
)
from sdfr.protocol.limits import ByteCredit, KeyedBuckets, TokenBucket
from sdfr.protocol.peers import Conflict, Counters, Peer, _GroupPing, _Ping
from sdfr.records.model import Service, service_digest
from sdfr.wire import MAX_SEQ, WIRE_COMPACT, WIRE_FULL, Origin


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
        #: Invitations to challenge us (`challenges.invite`): one a beacon period.
        self._invites = TokenBucket(1.0 / config.beacon_interval, 1.0)
        #: What each address sent us and we did not spend on answers to it yet: all an address
        #: that has not proven a round trip may get from us (no amplification).
        self._credit = ByteCredit(CREDIT_CAP, MAX_SOURCES)
        #: Bytes of services held in sets not yet believed (`UNPROVEN_BYTES` in all).
        self._held_bytes = 0
        self._own_challenge_at = -math.inf
        #: The time of the input being handled (what `sending.emit` judges proofs against).
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
        #: Announcements of our set saved up (`CoreConfig.update_burst`, `update_gap`).
        self._update_budget = TokenBucket(1.0 / max(config.update_gap, 1e-9), config.update_burst)
        self._dictionary_cache: tuple[int, bytes] | None = None
        #: The last multicast deltas' own steps, (base, version, body), oldest first, while
        #: each followed the one before: what the next delta carries when repairing.
        self._steps: list[tuple[int, int, bytes]] = []
        #: When a peer last asked for a catch-up (what changed since a set it holds).
        self._repair_asked = -math.inf
        #: Beacons sent as pings, by sequence number.
        self._group_pings: dict[int, _GroupPing] = {}
        #: Pings and beacon pings past their timeout (settled lost), kept until their proof
        #: window ends: a late answer (a busy robot) still proves its robot alive when the
        #: ping went (`trust.take_proof`).  At most MAX_PINGS of each (`beacons.keep_late`).
        self._late: dict[int, _Ping] = {}
        self._late_groups: dict[int, _GroupPing] = {}
        #: Address -> the wire version of the peer there (what unicasts to it may be).
        self._wire_at: dict[Addr, int] = {}

    # -- what the protocol's modules read of it and share ------------------------------

    def _nonce(self, turns: int = 1, turn: int = 0) -> int:
        """A fresh random 64-bit sequence number for a ping (its answer proves the round trip
        happened now), of the given turn (`answers_beacon`: its value modulo `turns`)."""
        seq = self.rng.getrandbits(64)
        if turns > 1:
            seq = seq - seq % turns + turn
            if seq > MAX_SEQ:
                seq -= turns
        return seq

    def _advertised(self) -> tuple[int, tuple[Service, ...], str]:
        """The set we tell of: the last announced, or before `start` the local one."""
        if self._announced is None:
            return self.version, self.services, self.digest
        return self._announced

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

    @property
    def ssdp_interop(self) -> bool:
        return auth.plain_ssdp_answered(self.config.ssdp_interop, self.keyring)

    def _address_proven(self, addr: Addr, now: float) -> bool:
        """Whether `addr` answered a ping of ours lately: it may get more than it sent."""
        t = self._answered.get(addr)
        return t is not None and now - t <= self.config.proven_for

    def _own_host(self) -> str | None:
        try:
            return urlsplit(self.location).hostname
        except ValueError:
            return None

    def _me(self) -> str:
        return f"uuid:{self.config.robot_id}"

    def _drop_fetch(self, peer: Peer) -> None:
        if peer.fetch is not None:
            self._held_bytes -= peer.fetch.size
            peer.fetch = None

    _EMPTY = service_digest(())

    def _empty_digest(self) -> str:
        return self._EMPTY
