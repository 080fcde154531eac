"""What a robot knows of others: peers, fetches and pings in flight, conflicts, counters."""

from __future__ import annotations

import math
from collections import Counter, deque
from dataclasses import dataclass, field

from sdfr.protocol.auth import ReplayWindow
from sdfr.protocol.config import Addr
from sdfr.records.model import Service
from sdfr.wire import Update


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
    #: Bytes of the services' JSON held (what an unbelieved set costs the budget).
    size: int = 0

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
class _GroupPing:
    """A beacon that is also a ping: the peers expected to answer it, at their addresses."""

    sent: float
    targets: dict[str, Addr]
    #: Robots that answered it (its nonce proves a round trip once per robot, a peer it did
    #: not expect included: after a merge the first beacon each side hears proves the other).
    heard: set[str] = field(default_factory=set)


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
    #: Answered a ping of ours in this run, at its current boot: its boot, version, digest and
    #: address are what its answers said.  Only then is it listed, pinged and fetched from.
    proven: bool = False
    #: In the history map (saved): proven at some time, in this run or an earlier one.
    known: bool = False
    #: When it last answered a ping of ours (the proof that keeps it listed reachable).
    answered_at: float = -math.inf
    #: When the ping was sent whose answer was last believed (later answers only, `trust.prove`).
    asked_at: float = -math.inf
    #: When it last said something not believed yet (challenged until it answers or stops).
    claimed_at: float = -math.inf
    #: Where that claim came from (where its challenge goes).
    claim_addr: Addr | None = None
    #: (boot, version, digest) the `services` below belong to; None when we hold no set.
    held: tuple[int, int, str] | None = None
    services: tuple[Service, ...] = ()
    byebye_boot: int | None = None
    pings: deque[bool] = field(default_factory=deque)
    rtt: float | None = None
    #: The smoothed RTT in the last view handed out (stored, listed).
    rtt_told: float | None = None
    next_ping: float = math.inf
    fetch: _Fetch | None = None
    window: ReplayWindow = field(default_factory=ReplayWindow)
    challenged_at: float = -math.inf
    #: A fetch it asked for before its address was proven: (address, parts wanted or None).
    deferred: tuple[Addr, tuple[int, ...] | None] | None = None
    #: The wire version it speaks, as its last datagram said (sdfr.wire.WIRE_*).
    wire: int = 1
    #: `sdfr.wire.delta_dictionary` of the set we hold, for its packed deltas: (held, bytes).
    dictionary: tuple[tuple[int, int, str], bytes] | None = None
    #: The last delta announcing a set not yet believed, applied if its answer confirms it.
    held_delta: Update | None = None

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
    #: Invitations to challenge us sent (`challenges.invite`): robots whose first beacon did not
    #: pay for our challenge.
    invites: int = 0
