"""Beacons and pings: the beacon (a ping to the fleet, by turns in a large one), unicast
pings and their schedule, round trips and the indicator (the window of settled pings)."""

from __future__ import annotations

import math
from typing import TypeVar

from sdfr import wire
from sdfr.protocol import sending
from sdfr.protocol.config import CHALLENGE_PAD, MAX_PINGS, Addr, answers_beacon
from sdfr.protocol.peers import Peer, _GroupPing, _Ping
from sdfr.protocol.state import CoreState
from sdfr.wire import WANT_ALL, WIRE_COMPACT, Alive, Discovery

P = TypeVar("P", _Ping, _GroupPing)

#: A peer's smoothed RTT is stored (and listed) again once it moved from the stored one by more
#: than this share of it and this many seconds: a true figure without a write per round trip.
RTT_TELL_SHARE = 0.2
RTT_TELL_S = 0.002
#: A reachable peer whose answers stop coming is pinged once every 1/REPROVE_PINGS of its proof
#: window over the last two thirds of it (16 pings): the chance that a live robot on a link
#: losing 30 % each way misses them all is 0.51 ** 16, about one in 50,000.
REPROVE_PINGS = 24


def beacon_pings(core: CoreState) -> bool:
    """Whether our beacons are also pings (to the peers that answer them, `by_beacon`)."""
    return core.config.wire_compact and core.config.ping_interval >= core.config.beacon_interval


def by_beacon(core: CoreState, peer: Peer) -> bool:
    """Whether `peer` is pinged by our beacons rather than by unicast: it speaks wire 2
    (so it answers them) and is proven.  One multicast pings the whole fleet, and a round
    trip costs one datagram each way instead of a unicast ping and its reply."""
    return beacon_pings(core) and peer.proven and peer.wire >= WIRE_COMPACT


def schedule_ping(core: CoreState, peer: Peer, now: float) -> None:
    """The first ping to a proven peer that became reachable: a random part of a period
    away, or none by unicast when beacons ping it."""
    if by_beacon(core, peer):
        peer.next_ping = math.inf
    else:
        peer.next_ping = now + core.rng.uniform(0.1, 1.0) * core.config.ping_interval


def new_ping(core: CoreState, peer: Peer, now: float, dst: Addr, *, challenge: bool = False) -> int:
    """A ping to `peer` at `dst` sent now (its sequence number); the next is a period away."""
    seq = core._nonce()
    core._pings[seq] = _Ping(peer.robot_id, now, dst, challenge)
    jitter = core.rng.uniform(1 - core.config.jitter, 1.0)
    if peer.proven and by_beacon(core, peer):
        peer.next_ping = math.inf
    elif peer.proven:
        peer.next_ping = now + core.config.ping_interval * jitter
    else:  # challenged again after a ping timeout until it answers (a lossy link may
        # lose a few round trips in a row; CHALLENGE_RATE bounds what fakes can cost)
        peer.next_ping = now + core.config.ping_timeout * (2 - jitter)
    return seq


def ping(
    core: CoreState,
    peer: Peer,
    now: float,
    *,
    addr: Addr | None = None,
    challenge: bool = False,
    pad: bool = False,
) -> bool:
    """Ping `peer` (at `addr`); False if it could not go (see `sending.emit`).  `pad`: see
    CHALLENGE_PAD."""
    dst = peer.address if addr is None else addr
    if len(core._pings) >= MAX_PINGS:
        core.counters.challenges_limited += 1
        return False
    seq = new_ping(core, peer, now, dst, challenge=challenge)
    ping = Discovery(core._origin(), f"uuid:{peer.robot_id}", 0, seq=seq, multicast=False)
    # (In the form the robot reads, wherever it is: a robot met at a new address gets the
    # small ping, which its first datagram from there pays for.)
    compact = core.config.wire_compact and peer.wire >= WIRE_COMPACT
    extra = CHALLENGE_PAD if pad else 0
    if sending.send(core, ping, dst, to=peer.robot_id, compact=compact, pad=extra):
        return True
    del core._pings[seq]
    return False


def settle_ping(core: CoreState, peer: Peer, *, ok: bool) -> None:
    before = peer.indicator
    peer.pings.append(ok)
    while len(peer.pings) > core.config.ping_window:
        peer.pings.popleft()
    if peer.indicator != before:
        core._dirty.add(peer.robot_id)


def keep_late(table: dict[int, P], seq: int, ping: P) -> None:
    """A ping settled lost at its timeout, kept in `table` (`CoreState._late`...) for a late
    answer; the oldest goes beyond MAX_PINGS."""
    table[seq] = ping
    while len(table) > MAX_PINGS:
        del table[next(iter(table))]


def drop_late(core: CoreState, now: float, window: float) -> None:
    """Forget the late pings whose proof window has ended: an answer now would prove
    nothing that lists a robot."""
    for table in (core._late, core._late_groups):
        for seq in [s for s, p in table.items() if now >= p.sent + window]:
            del table[seq]


def round_trip(core: CoreState, peer: Peer, sample: float, src: Addr, now: float) -> None:
    peer.rtt = sample if peer.rtt is None else 0.8 * peer.rtt + 0.2 * sample
    told = peer.rtt_told
    if told is None or abs(peer.rtt - told) > max(RTT_TELL_S, RTT_TELL_SHARE * told):
        core._dirty.add(peer.robot_id)  # the stored and listed RTT is no longer true
    core._answered[src] = now
    settle_ping(core, peer, ok=True)


def reprove_at(core: CoreState, peer: Peer, window: float) -> float:
    """When a reachable peer whose answers went missing is pinged again."""
    return max(peer.answered_at + window / 3, peer.challenged_at + window / REPROVE_PINGS)


def beacon(core: CoreState, now: float) -> None:
    """The beacon; with beacon pings, a ping to every peer that answers them too (or, in
    a fleet of more than `beacon_answers` such peers, to those whose turn it is)."""
    cfg = core.config
    compact = core._compact_for(None)
    seq, turns = None, 1
    if beacon_pings(core):
        pinged = {
            p.robot_id: p.address for p in core.peers.values() if p.reachable and by_beacon(core, p)
        }
        if compact and len(pinged) > cfg.beacon_answers:
            turns = min(wire.MAX_TURNS, -(-len(pinged) // max(1, cfg.beacon_answers)))
        core._turns = turns
        seq = core._nonce()
        targets = pinged
        for _ in range(turns if turns > 1 else 0):
            # The next turn in order that has peers in it, as the seq says.
            core._beacon_turn = (core._beacon_turn + 1) % turns
            seq = core._nonce(turns, core._beacon_turn)
            targets = {rid: addr for rid, addr in pinged.items() if answers_beacon(rid, seq, turns)}
            if targets:
                break
        if targets or core.peers:
            # (Expecting no answer, it still proves the peers out of reach that hear it and
            # answer: after a merge the first beacon heard on each side lists the other.)
            core._group_pings[seq] = _GroupPing(now, targets)
        else:
            seq, turns = None, 1
    if compact:  # peers know where we are: no LOCATION, no max-age
        sending.send(core, Alive(core._origin(), "", 0, seq, turns), None, compact=True)
    else:
        sending.send(
            core, Alive(core._origin(), core.location, cfg.max_age, seq), None, compact=False
        )


def beacon_period(core: CoreState) -> float:
    return core.config.beacon_interval * core.rng.uniform(1 - core.config.jitter, 1.0)


def search(core: CoreState, now: float) -> None:
    cfg = core.config
    search = Discovery(core._origin(), wire.fleet_target(cfg.fleet), cfg.mx, want=WANT_ALL)
    sending.send(core, search, None, compact=False)  # a multicast search is always a full one
