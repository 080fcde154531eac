"""The protocol's limits and timing: its constants and `CoreConfig`."""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass

from sdfr import wire

#: A unicast destination; `None` in an outgoing datagram means the multicast group.
Addr = tuple[str, int]
Outgoing = tuple[bytes, Addr | None]


#: Robots the history map holds at most; when full, the one silent longest is forgotten.
MAX_PEERS = 1024
#: Robots heard but never proven by a round trip in this run (and not in the history map),
#: held at most.
MAX_UNPROVEN = 256
#: Update parts held for robots whose set is not yet believed (unproven robots, new boots,
#: new versions), shared among them (but at least UNPROVEN_PARTS_MIN each); the rest is
#: fetched once the robot answers.
UNPROVEN_PARTS = 512
UNPROVEN_PARTS_MIN = 4
#: And in bytes of the services' JSON (a deflated part may inflate to far more than it took
#: on the air), in all: what fakes that never answer can make a robot hold.
UNPROVEN_BYTES = 2 * 1024 * 1024
#: Challenges sent at most, per second and in a burst, to all addresses together.
CHALLENGE_RATE = 20.0
CHALLENGE_BURST = 128.0
#: Bytes a challenge to a robot that may not have proven us is padded by: its answer with its
#: own challenge riding on it (a compact reply with X-SDFR-PING) is about 30 bytes longer than
#: a compact ping, more when the answerer's id is the longer one.
CHALLENGE_PAD = 64
#: A robot that just answered a challenge is challenged again no sooner than this.
CHALLENGE_GAP = 0.05
#: And to one address, per second and in a burst (many robots claimed at one address cost
#: that address no more).
ADDR_CHALLENGE_RATE = 1.0
ADDR_CHALLENGE_BURST = 3.0
#: Pings in flight at most (each waits a ping timeout for its answer).
MAX_PINGS = 4096
#: Bytes received from an address and not yet answered, kept per address at most: the most a
#: robot may send to an address that has not proven a round trip.
CREDIT_CAP = 64 * 1024
#: Datagrams read from one source address, per second and in a burst; the rest are dropped
#: unread.  A whole set of 255 parts fits in the burst.
SOURCE_RATE = 500.0
SOURCE_BURST = 1000.0
MAX_SOURCES = 4096
#: Plain SSDP searches answered at most, per second and in a burst (ssdp_interop), in all
#: and from one source address.
PLAIN_RATE = 10.0
PLAIN_BURST = 20.0
PLAIN_SOURCE_RATE = 0.5
PLAIN_SOURCE_BURST = 1.0
#: Whole sets multicast in answer to searches at most once in this many seconds, and at most
#: once a beacon period.
MCAST_SET_GAP = 1.0
#: Update parts one address is served at most, per second, in whole sets of ours.
FETCH_SETS_PER_S = 2.0
#: Searchers one multicast answer collects at most.
MAX_REPLY_TO = 64
#: For this many seconds after a peer asked for a catch-up (it missed a delta: links lose
#: datagrams here), each multicast delta also carries the steps of the last DELTA_STEPS - 1
#: before it, so that a robot that missed those applies it without asking.
REPAIR_MEMORY = 60.0
DELTA_STEPS = 2


#: The product's protocol defaults, written here once: `CoreConfig` and sdfrd's `Config`
#: (its flags, TOML keys and help) take them from here.
BEACON_INTERVAL = 10.0  # the paper's
MISS_LIMIT = 3
PING_WINDOW = 20
REPLY_DELAY_MAX = 0.5
UPDATE_GAP = 0.25
UPDATE_BURST = 3
#: Most peers one beacon asks for a ping reply (`CoreConfig.beacon_answers`).
BEACON_ANSWERS = 20


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
    #: A change waits this long for the rest of a burst before it is announced (0: the next
    #: turn of the event loop, which already gathers what arrived together).
    update_coalesce: float = 0.0
    #: Changes are announced at once while `update_burst` announcements are saved up, one
    #: more each `update_gap` seconds (a token bucket): at the paper's churn (a change every
    #: 1.25 s) 98 % go out at once; a program's burst of changes goes out in `update_burst`
    #: announcements, then gathers, one announcement a gap.
    update_gap: float = UPDATE_GAP
    update_burst: int = UPDATE_BURST
    #: Robot-to-robot datagrams in the compact form (`sdfr.wire.encode`) to peers that read
    #: it, and the beacon as everyone's ping; False: only the full forms, as wire version 1.
    wire_compact: bool = True
    #: A beacon that pings asks at most about this many peers to answer: in a larger fleet
    #: the peers take turns (`answers_beacon`), so that what a robot sends and receives for
    #: the indicator does not grow with the fleet (each pair is then measured every
    #: ceil(peers / beacon_answers) beacons).
    beacon_answers: int = BEACON_ANSWERS
    #: Announced sets kept, so that a robot that missed a change or a few is sent what changed
    #: since the set it holds rather than the whole set.
    delta_history: int = 32
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
    def mcast_set_gap(self) -> float:
        return max(MCAST_SET_GAP, self.beacon_interval)

    def proof_window(self, turns: int = 1) -> float:
        """How long a peer's last answer to a ping of ours keeps it listed reachable: the miss
        limit of its ping periods (a beacon period times the turns its peers take, when beacons
        are the pings)."""
        period = self.ping_interval
        if self.wire_compact and self.ping_interval >= self.beacon_interval:
            period = max(period, self.beacon_interval * max(1, turns))
        return max(self.dead_after, self.miss_limit * period)

    @property
    def proven_for(self) -> float:
        """How long an answered ping vouches for its address."""
        return max(2 * self.ping_interval, self.dead_after)


def answers_beacon(robot_id: str, seq: int, turns: int) -> bool:
    """Whether the robot `robot_id` answers a beacon of sequence number `seq` whose peers
    take `turns` turns (`sdfr.wire.Alive.turns`): its turn is a hash of its id."""
    return turns <= 1 or zlib.crc32(robot_id.encode()) % turns == seq % turns
