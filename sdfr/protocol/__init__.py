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

Trust (see also sdfr.protocol.auth, and docs/security.md for each claim's test):
- Pings and pinging beacons carry a 64-bit random nonce; only a robot's answer to one of ours,
  from where the ping went, changes what is believed of it (boot, version, digest, address),
  and a robot is listed reachable only while it answered lately.  A robot never heard, a new,
  lower or reused boot, another address and every peer after a restart of ours are challenged
  first; their Update parts may be held (bounded) and are applied once the answer names that
  set.  A lower or reused boot that answers is believed at once: nothing is locked out.
- With a fleet key every datagram goes out sealed for its recipient (or the fleet) and from
  its sender's address; one whose seal fails, that is for another robot or that comes from
  elsewhere is dropped before it is parsed, and a proven peer's counter seen already (a
  replay) right after.
- At most MAX_UNPROVEN robots not yet proven are held, and MAX_PEERS in all.
- An address that has not answered a ping of ours never gets more bytes than it sent
  (`_credit`); searches cost at most one whole-set multicast a beacon period.  Work is bounded
  per source address (SOURCE_RATE), and challenges per address and in all (CHALLENGE_RATE).

The package: `config` (limits, timing), `peers` (what a robot knows of others), `state`
(the core's state, and what every part reads of it), `core` (`Core`: the entry points and
what arrives), and the parts `Core` drives, plain functions of the state: `sending` (encode,
seal, bound the bytes), `beacons` (beacons, pings, round trips, the indicator), `challenges`
(challenges, invitations, ping replies, our own id), `trust` (the gate, proofs, the peer
table), `updates` (announcing, serving and fetching service sets, deltas, catch-up), `plain`
(plain SSDP clients) and `timers` (what is due when).  Beside the core, and imported by
it or by the daemon on their own: `auth` (the keyring, seals, replay windows), `limits`
(token buckets) and `addressing` (address self-configuration, another automaton).
"""

from __future__ import annotations

from sdfr.protocol.config import (
    ADDR_CHALLENGE_BURST,
    ADDR_CHALLENGE_RATE,
    BEACON_ANSWERS,
    BEACON_INTERVAL,
    CHALLENGE_BURST,
    CHALLENGE_GAP,
    CHALLENGE_RATE,
    CREDIT_CAP,
    FETCH_SETS_PER_S,
    MAX_PEERS,
    MAX_PINGS,
    MAX_REPLY_TO,
    MAX_SOURCES,
    MAX_UNPROVEN,
    MCAST_SET_GAP,
    MISS_LIMIT,
    PING_WINDOW,
    PLAIN_BURST,
    PLAIN_RATE,
    PLAIN_SOURCE_BURST,
    PLAIN_SOURCE_RATE,
    REPLY_DELAY_MAX,
    SOURCE_BURST,
    SOURCE_RATE,
    UNPROVEN_BYTES,
    UNPROVEN_PARTS,
    UNPROVEN_PARTS_MIN,
    Addr,
    CoreConfig,
    Outgoing,
    answers_beacon,
)
from sdfr.protocol.core import Core
from sdfr.protocol.peers import Conflict, Counters, Peer

__all__ = [
    "ADDR_CHALLENGE_BURST",
    "ADDR_CHALLENGE_RATE",
    "BEACON_ANSWERS",
    "BEACON_INTERVAL",
    "CHALLENGE_BURST",
    "CHALLENGE_GAP",
    "CHALLENGE_RATE",
    "CREDIT_CAP",
    "FETCH_SETS_PER_S",
    "MAX_PEERS",
    "MAX_PINGS",
    "MAX_REPLY_TO",
    "MAX_SOURCES",
    "MAX_UNPROVEN",
    "MCAST_SET_GAP",
    "MISS_LIMIT",
    "PING_WINDOW",
    "PLAIN_BURST",
    "PLAIN_RATE",
    "PLAIN_SOURCE_BURST",
    "PLAIN_SOURCE_RATE",
    "REPLY_DELAY_MAX",
    "SOURCE_BURST",
    "SOURCE_RATE",
    "UNPROVEN_BYTES",
    "UNPROVEN_PARTS",
    "UNPROVEN_PARTS_MIN",
    "Addr",
    "Conflict",
    "Core",
    "CoreConfig",
    "Counters",
    "Outgoing",
    "Peer",
    "answers_beacon",
]
