"""What is due when: the timer's work (searches, announcements, replies, beacons, pings,
challenges, fetches, expiry) and the next deadline."""

from __future__ import annotations

import math

from sdfr.protocol import beacons, challenges, trust, updates
from sdfr.protocol.config import CHALLENGE_RATE
from sdfr.protocol.state import CoreState


def handle_timer(core: CoreState, now: float) -> None:
    """Do whatever is due at `now`."""
    if not core._started or core._stopped:
        return
    core._now = now
    cfg = core.config
    if now >= core._discovery_repeat:
        core._discovery_repeat = math.inf
        beacons.search(core, now)
    if now >= core._update_at:
        core._update_at = math.inf
        updates.announce_change(core, now)
    if now >= core._reply_at:
        updates.flush_replies(core, now)
    if now >= core._next_beacon:
        beacons.beacon(core, now)
        core._next_beacon = now + beacons.beacon_period(core)
    if now >= core._next_prune:
        prune(core, now)
    window = cfg.proof_window(core._turns)
    beacons.drop_late(core, now, window)
    expired = [seq for seq, p in core._pings.items() if now >= p.sent + cfg.ping_timeout]
    for seq in expired:
        ping = core._pings.pop(seq)
        beacons.keep_late(core._late, seq, ping)
        peer = core.peers.get(ping.robot_id)
        if peer is not None and ping.addr == peer.address and peer.proven:
            # (A challenge to another address, or to a robot not proven yet, says nothing
            # of the peer's link.)
            beacons.settle_ping(core, peer, ok=False)
    late = [s for s, g in core._group_pings.items() if now >= g.sent + cfg.ping_timeout]
    for seq in late:
        group = core._group_pings.pop(seq)
        beacons.keep_late(core._late_groups, seq, group)
        for robot_id, addr in group.targets.items():
            peer = core.peers.get(robot_id)
            if peer is not None and addr == peer.address:
                beacons.settle_ping(core, peer, ok=False)
    if core.conflict is not None and now >= core.conflict.last_seen + cfg.dead_after:
        core.conflict = None  # no second daemon has answered for a miss window
    for peer in list(core.peers.values()):
        if not peer.known and now >= peer.last_heard + cfg.dead_after:
            trust.forget(core, peer)
            continue
        if peer.reachable and (
            now >= peer.answered_at + window or now >= peer.last_heard + cfg.dead_after
        ):
            # Silent for the miss limit, or no answer to our pings for a miss window:
            # whatever else arrives in its name (a replay, a relay, a late datagram) does
            # not keep it listed.
            peer.reachable = False
            peer.next_ping = math.inf
            core._drop_fetch(peer)
            core._dirty.add(peer.robot_id)
            continue
        if not peer.proven and now >= peer.next_ping:
            if now < peer.claimed_at + cfg.dead_after:
                challenges.challenge(core, peer, peer.address, now)
                peer.next_ping = max(peer.next_ping, now + 1.0 / CHALLENGE_RATE)
            else:
                peer.next_ping = math.inf
        elif trust.doubted(core, peer, now):
            # A claim it has not confirmed yet, whose challenge had to wait (one had just
            # been answered): ask now.
            addr = peer.claim_addr or peer.address
            if not challenges.challenge(core, peer, addr, now, pad=not peer.reachable):
                peer.challenged_at = now  # (no budget or bytes for it: a timeout later)
        elif peer.reachable and now >= peer.next_ping:
            beacons.ping(core, peer, now)
        elif peer.reachable and now >= beacons.reprove_at(core, peer, window):
            # Its answers went missing lately (a lossy link): ask it alone, REPROVE_PINGS
            # times in what is left of its window, so that only a robot really gone (or
            # a link really down) runs out of it.
            peer.challenged_at = now
            if core._challenge_budget.take(now):
                beacons.ping(core, peer, now, challenge=True)
        if peer.fetch is not None and now >= peer.fetch.retry_at:
            updates.request_fetch(core, peer, now)


def next_deadline(core: CoreState) -> float | None:
    """When `handle_timer` must run next (None: only an input can change anything)."""
    if not core._started or core._stopped:
        return None
    cfg = core.config
    t = min(
        core._next_beacon,
        core._discovery_repeat,
        core._update_at,
        core._reply_at,
        core._next_prune,
    )
    for ping in core._pings.values():
        t = min(t, ping.sent + cfg.ping_timeout)
    for group in core._group_pings.values():
        t = min(t, group.sent + cfg.ping_timeout)
    if core.conflict is not None:
        t = min(t, core.conflict.last_seen + cfg.dead_after)
    window = cfg.proof_window(core._turns)
    for peer in core.peers.values():
        if peer.reachable:
            t = min(
                t,
                peer.answered_at + window,
                peer.last_heard + cfg.dead_after,
                peer.next_ping,
                beacons.reprove_at(core, peer, window),
            )
        elif not peer.proven:
            t = min(t, peer.next_ping)
        retry = peer.challenged_at + cfg.ping_timeout
        if (
            peer.proven
            and peer.answered_at < peer.claimed_at
            and retry < (peer.claimed_at + cfg.dead_after)
        ):
            t = min(t, retry)  # (`trust.doubted`)
        if not peer.known:
            t = min(t, peer.last_heard + cfg.dead_after)
        if peer.fetch is not None:
            t = min(t, peer.fetch.retry_at)
    return None if t == math.inf else t


def prune(core: CoreState, now: float) -> None:
    horizon = now - core.config.proven_for
    for addr in [a for a, t in core._answered.items() if t < horizon]:
        del core._answered[addr]
    core._wire_at = {p.address: p.wire for p in core.peers.values()}
    # What unbelieved sets hold, counted again (the running count is only bookkeeping).
    core._held_bytes = sum(p.fetch.size for p in core.peers.values() if p.fetch is not None)
    core._next_prune = now + core.config.proven_for
