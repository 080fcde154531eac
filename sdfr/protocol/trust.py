"""Whom to trust: the gate every datagram of a robot passes (believed, held, or
refused), what a proof (an answer to our nonce) makes us believe, and the peer table's room."""

from __future__ import annotations

import math

from sdfr import wire
from sdfr.protocol import beacons, challenges
from sdfr.protocol.auth import Sealed
from sdfr.protocol.config import CHALLENGE_GAP, MAX_PEERS, MAX_UNPROVEN, Addr
from sdfr.protocol.peers import Peer
from sdfr.protocol.state import CoreState
from sdfr.wire import Origin, Response


def gate(
    core: CoreState,
    origin: Origin,
    src: Addr,
    now: float,
    seal: Sealed | None,
    proof: float | None,
    *,
    ping: bool = False,
) -> tuple[Peer | None, bool]:
    """The peer a datagram speaks for (None: refused), and whether what it says may be
    believed now.

    Only a peer's answer to a ping of ours (`proof`: when it proves the peer alive,
    `take_proof`; its nonce makes it fresh) changes what we believe of it: its boot,
    version, digest and address.  Anything else from a robot not proven in this run, of
    another boot or from another address is not believed but answered with a challenge;
    its Update parts may be held until the answer comes.
    A sealed datagram whose counter was seen already in the proven boot is a replay.
    """
    peer = core.peers.get(origin.robot_id)
    if peer is None:
        refused = admit(core, now)
        if refused is not None:
            return refuse(core, refused)
        peer = core.peers[origin.robot_id] = Peer(
            robot_id=origin.robot_id,
            address=src,
            location="",
            first_seen=now,
            last_heard=now,
            boot_id=origin.boot_id,
            version=origin.version,
            digest=origin.digest,
        )
        core._unproven += 1
    if proof is not None:
        prove(core, peer, origin, src, now, proof)
        if seal is not None:
            if not peer.window.fresh(origin.boot_id, seal.counter):
                # A boot id used again (its state lost), whose new counters are below
                # the old ones: the answer is fresh by its nonce, so its counter is too.
                peer.window.reset()
            peer.window.accept(origin.boot_id, seal.counter)
        return peer, True
    if not peer.proven:
        # Never proven in this run (a new robot, or one of the history map): say nothing
        # of it until it answers.  (The claim goes where its datagram came from.)
        core.counters.rejects["unproven"] += 1
        peer.claimed_at = now
        if not peer.known:  # (a robot of the history map keeps its record as it was)
            peer.last_heard = now
            peer.address = src
            peer.wire = origin.wire  # (only the form of what we send it)
        if not ping:  # (a ping's answer carries our challenge: `challenges.answer_ping`)
            challenges.challenge(core, peer, src, now)
        return peer, False
    if seal is not None and origin.boot_id == peer.boot_id:
        if not peer.window.fresh(origin.boot_id, seal.counter):
            return refuse(core, "replay")
        peer.window.accept(origin.boot_id, seal.counter)
    if src != peer.address:
        # A robot moves only to where it answers a challenge: a datagram sent again
        # from elsewhere must not move it (nor bring a dead one back there).  (A listed
        # robot that moved knows us: its answer needs no room for a challenge of ours.)
        doubt(core, peer, src, now, pad=not peer.reachable)
        refuse(core, "other-address")
        return peer, False
    if origin.boot_id != peer.boot_id:
        # A new boot, an earlier life's datagram (late or replayed), or a robot that lost
        # its state (and its clock): only its answer to a challenge tells.  (A newer boot
        # is asked at once: a challenge still in flight went to its dead predecessor.)
        doubt(core, peer, src, now, urgent=origin.boot_id > peer.boot_id)
        refuse(core, "stale-boot" if origin.boot_id < peer.boot_id else "unproven")
        return peer, False
    if peer.byebye_boot == origin.boot_id:
        # After a Byebye only an answer to our challenge brings that boot back (a Byebye
        # anyone could have sent must not lock a robot out).
        doubt(core, peer, src, now)
        refuse(core, "after-byebye")
        return peer, False
    return peer, True


def refuse(core: CoreState, reason: str) -> tuple[None, bool]:
    core.counters.rejects[reason] += 1
    return None, False


def admit(core: CoreState, now: float) -> str | None:
    """Make room for a new robot; the reason it cannot have any, else None."""
    if core._unproven >= MAX_UNPROVEN:
        return "unproven-full"
    if len(core.peers) < MAX_PEERS:
        return None
    gone = [p for p in core.peers.values() if not p.reachable]
    if not gone:
        return "peers-full"
    oldest = min(gone, key=lambda p: p.last_heard)
    forget(core, oldest)
    if oldest.known:
        core._removed.add(oldest.robot_id)
    return None


def forget(core: CoreState, peer: Peer) -> None:
    del core.peers[peer.robot_id]
    core._drop_fetch(peer)
    if not peer.known:
        core._unproven -= 1
    core._dirty.discard(peer.robot_id)
    for pings in (core._pings, core._late):
        for seq in [s for s, p in pings.items() if p.robot_id == peer.robot_id]:
            del pings[seq]


def prove(core: CoreState, peer: Peer, origin: Origin, src: Addr, now: float, alive: float) -> None:
    """The peer answered a ping of ours from `src`: believe what it says of itself now.  The
    answer proves it alive at `alive` (now, or when the ping went for a late answer)."""
    if (
        origin.boot_id != peer.boot_id
        or origin.version < peer.version
        or (origin.version == peer.version and origin.digest != peer.digest)
    ):
        # A new boot, or a new life under a boot id used again (its state was lost, and
        # its versions start over): nothing of the set we hold is its set now.
        new_boot(core, peer, origin)
    elif (origin.version, origin.digest) != (peer.version, peer.digest):
        peer.version, peer.digest = origin.version, origin.digest
        core._dirty.add(peer.robot_id)
    peer.byebye_boot = None
    peer.answered_at = max(peer.answered_at, alive)
    # Answered: the next claim (a change right behind this one) may be asked about soon,
    # not a ping timeout later; CHALLENGE_GAP bounds what forged claims cost it.
    challenge_soon(core, peer, now)
    if not peer.proven:
        peer.proven = True
        if not peer.known:
            peer.known = True
            core._unproven -= 1
        core._dirty.add(peer.robot_id)
    if peer.address != src:
        peer.address = src
        core._dirty.add(peer.robot_id)
    if not peer.reachable:
        peer.reachable = True
        core.arrivals += 1
        # The ping window is kept: the pings lost while the peer was away are part of its
        # link's record, and the window slides them out as new pings settle.
        beacons.schedule_ping(core, peer, now)
        core._dirty.add(peer.robot_id)


def new_boot(core: CoreState, peer: Peer, origin: Origin) -> None:
    """The peer restarted: its old service set goes, never merged with the new one."""
    peer.boot_id, peer.version, peer.digest = origin.boot_id, origin.version, origin.digest
    peer.held = None
    peer.services = ()
    peer.dictionary = None
    peer.byebye_boot = None
    peer.window.reset()
    core._dirty.add(peer.robot_id)


def challenge_soon(core: CoreState, peer: Peer, now: float) -> None:
    """Let `peer` be challenged again CHALLENGE_GAP after now, not a ping timeout after its
    last challenge."""
    peer.challenged_at = min(peer.challenged_at, now - core.config.ping_timeout + CHALLENGE_GAP)


def heard(
    core: CoreState,
    peer: Peer,
    origin: Origin | None,
    src: Addr,
    now: float,
    location: str | None,
    proof: bool,
) -> None:
    """Record a sign of life from a peer `gate` let through: its datagram came from its
    proven address (or is its answer to a ping of ours, `proof`)."""
    if (
        origin is not None
        and not proof
        and ((origin.version, origin.digest) != (peer.version, peer.digest) or not peer.reachable)
    ):
        # A change of its set, or a robot whose last answer is too old to list it: only
        # its answer to a ping (fresh by construction) is believed.  (One that is not
        # listed may not list us either: the challenge pays for its own, `CHALLENGE_PAD`.)
        doubt(core, peer, src, now, pad=not peer.reachable)
    peer.last_heard = now
    if origin is not None and origin.wire != peer.wire:
        peer.wire = origin.wire
        if peer.reachable and beacons.by_beacon(core, peer):
            peer.next_ping = math.inf  # its beacon pings stand in for unicast ones now
    if origin is not None:
        core._wire_at[src] = origin.wire
    if location and location != peer.location:
        peer.location = location
        core._dirty.add(peer.robot_id)


def doubted(core: CoreState, peer: Peer, now: float) -> bool:
    """Whether a proven peer said something we have not seen it confirm, and may be
    challenged about it now."""
    return (
        peer.proven
        and peer.answered_at < peer.claimed_at
        and now < peer.claimed_at + core.config.dead_after
        and now >= peer.challenged_at + core.config.ping_timeout
    )


def doubt(
    core: CoreState, peer: Peer, src: Addr, now: float, *, pad: bool = True, urgent: bool = False
) -> None:
    """A claim of `peer`'s we do not believe on its word: challenge it (at `src`), now or
    as soon as its last challenge allows (`doubted`); `urgent`: CHALLENGE_GAP after it."""
    peer.claimed_at = now
    peer.claim_addr = src
    if urgent:
        challenge_soon(core, peer, now)
    challenges.challenge(core, peer, src, now, pad=pad)


def take_proof(
    core: CoreState, msg: wire.Message, origin: Origin, src: Addr, now: float
) -> float | None:
    """When `msg` proves its robot alive, if it answers a ping of ours (its nonce) from
    where the ping went: now, or, for a late answer (after the ping timeout, within the
    proof window: a busy robot), when the ping was sent; None: it is no proof.  The ping is
    settled (used up) only then, so a forgery cannot take it away.  A late answer says
    nothing of the link (its ping was settled lost, `timers`): no round-trip time."""
    if not isinstance(msg, Response) or msg.seq is None:
        return None
    late = msg.seq not in core._pings and msg.seq not in core._group_pings
    window = core.config.proof_window(core._turns)
    pings = core._late if late else core._pings
    ping = pings.get(msg.seq)
    if ping is not None:
        if ping.robot_id != origin.robot_id or ping.addr != src:
            return None
        if late and now >= ping.sent + window:
            return None  # (its window is over: it lists no one; `timers` forgets it)
        del pings[msg.seq]
        peer = core.peers.get(origin.robot_id)
        if peer is not None:
            if not late and (ping.addr == peer.address or not peer.proven):
                beacons.round_trip(core, peer, now - ping.sent, src, now)
            else:
                core._answered[src] = now
        return proven_at(peer, ping.sent, now, late)
    group = (core._late_groups if late else core._group_pings).get(msg.seq)
    if group is None or origin.robot_id in group.heard:
        return None
    if late and now >= group.sent + window:
        return None
    peer = core.peers.get(origin.robot_id)
    expected = group.targets.get(origin.robot_id)
    if expected is not None:
        if expected != src:
            return None
        del group.targets[origin.robot_id]
    elif peer is None or peer.address != src:
        return None  # (a robot we do not know joins by its search and our challenge)
    group.heard.add(origin.robot_id)
    if peer is not None:
        if late:
            core._answered[src] = now
        else:
            beacons.round_trip(core, peer, now - group.sent, src, now)
    return proven_at(peer, group.sent, now, late)


def proven_at(peer: Peer | None, asked: float, now: float, late: bool) -> float | None:
    """`take_proof`'s answer for an answer to a ping sent at `asked`."""
    if not newest_answer(peer, asked):
        return None
    return asked if late else now


def newest_answer(peer: Peer | None, asked: float) -> bool:
    """Whether an answer to a ping sent at `asked` may be believed: not when an answer to
    a later ping was believed already (a late answer of an earlier life, held back by the
    network or an outsider, must not undo what its successor said)."""
    if peer is None:
        return True
    if asked < peer.asked_at:
        return False
    peer.asked_at = asked
    return True
