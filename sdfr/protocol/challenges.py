"""Challenges: pings whose answer settles a claim, the invitation to challenge us, the
compact ping reply (a challenge of ours riding on it), and a second daemon with our id."""

from __future__ import annotations

from dataclasses import replace

from sdfr import wire
from sdfr.protocol import beacons, sending
from sdfr.protocol.auth import Sealed
from sdfr.protocol.config import CHALLENGE_PAD, CHALLENGE_RATE, MAX_PINGS, Addr
from sdfr.protocol.peers import Conflict, Peer, _Ping
from sdfr.protocol.state import CoreState
from sdfr.wire import WIRE_COMPACT, Alive, Discovery, Origin, Response

#: The source of a datagram sent from no address (see `on_own_id`).
UNSPECIFIED = "0.0.0.0"


def challenge(core: CoreState, peer: Peer, addr: Addr, now: float, *, pad: bool = True) -> bool:
    """Ping `peer` at `addr` so that its answer settles a claim; False if none was sent.
    `pad` (CHALLENGE_PAD): the robot there may not have proven us (it is new, restarted,
    moved, or we were apart): the challenge pays for its answer with its own challenge
    riding on it, which it sends no unproven address more bytes than it got from there.

    One at a time per robot, at most one a ping timeout (but one to a new address of a robot
    whose challenge went to another, `elsewhere`); per address and in all at most
    ADDR_CHALLENGE_RATE and CHALLENGE_RATE; and to an address that has not proven a round
    trip, no more bytes than it sent (`sending.emit`): a flood of claims costs a bounded trickle.
    """
    if now < peer.challenged_at + core.config.ping_timeout and not elsewhere(core, peer, addr):
        return True  # one is in flight (or was just answered)
    if not core._address_proven(addr, now) and not core._addr_challenges.take(addr[0], now):
        core.counters.challenges_limited += 1
        return False
    if not core._challenge_budget.take(now):
        core.counters.challenges_limited += 1
        if not peer.proven:  # try again as soon as the budget allows
            peer.next_ping = min(peer.next_ping, now + 1.0 / CHALLENGE_RATE)
        return False
    if not beacons.ping(core, peer, now, addr=addr, challenge=True, pad=pad):
        if len(core._pings) < MAX_PINGS and not core._address_proven(addr, now):
            invite(core, now)  # (its address has not paid for the challenge yet)
        return False
    peer.challenged_at = now
    core.counters.challenges += 1
    return True


def elsewhere(core: CoreState, peer: Peer, addr: Addr) -> bool:
    """Whether the challenge in flight to `peer` went to another address than `addr`: a
    robot that moved does not answer where it was, and waiting out that challenge would
    keep it from being asked where it is now (both are still bounded per address and in
    all)."""
    out = {p.addr for p in core._pings.values() if p.robot_id == peer.robot_id and p.challenge}
    return bool(out) and addr not in out


def invite(core: CoreState, now: float) -> None:
    """Ask every robot that has not proven us to challenge us: an extra beacon, without a
    nonce, padded so that the challenge it draws (padded itself, `CHALLENGE_PAD`) costs
    no more than it brings.  Sent when a robot's first beacon does not pay for our
    challenge of it: the two meet within one round trip of the first beacon heard, not a
    beacon period later.  Robots that believe us take it as the beacon it is.  At most
    one a beacon period: a multicast is sent to no third party, and claims cost the group
    one datagram a period at most."""
    if not core._invites.take(now):
        return
    compact = core._compact_for(None)
    me = core._origin()
    # (In the beacon's own form: the compact one names no LOCATION, no max-age.)
    invite = Alive(me, "", 0) if compact else Alive(me, core.location, core.config.max_age)
    # The largest challenge a robot that has not proven us sends back: its id may be
    # longer than ours, its boot, version and nonce as long as they go.
    longest = max((len(p.robot_id) for p in core.peers.values() if not p.proven), default=0)
    them = replace(
        me,
        robot_id="x" * max(longest, len(me.robot_id)),
        boot_id=2**31 - 1,
        version=max(me.version, 10**6),
    )
    challenge = Discovery(them, core._me(), 0, seq=wire.MAX_SEQ, multicast=False)
    group, port = core.config.group, core.config.port
    size = len(wire.encode(invite, group=group, port=port, compact=compact))
    # (A unicast search names the robot's address: as long as an address goes.)
    far = "fe80::ffff:ffff:ffff:ffff" if ":" in group else "255.255.255.255"
    need = len(wire.encode(challenge, group=far, port=port, compact=compact))
    need += CHALLENGE_PAD + len(me.robot_id)  # (its seal names us, ours the fleet)
    if sending.send(core, invite, None, compact=compact, pad=need - size):
        core.counters.invites += 1


def answer_ping(core: CoreState, origin: Origin | None, seq: int, src: Addr, now: float) -> None:
    """The compact ping reply to `seq`, for the robot that pinged (from `src`); to a robot
    we have not proven, our own challenge rides on it when the bytes allow."""
    to = None if origin is None else origin.robot_id
    peer = None if to is None else core.peers.get(to)
    reply = Response(core._origin(), core._me(), "", 0, seq)
    # (The form its ping says it reads: the smallest answer.)
    compact = core.config.wire_compact and origin is not None and origin.wire >= WIRE_COMPACT
    if (
        peer is not None
        and (not peer.proven or not peer.reachable)
        and peer.address == src
        and now >= peer.challenged_at + core.config.ping_timeout
        and len(core._pings) < MAX_PINGS
    ):
        ride = core._nonce()
        core._pings[ride] = _Ping(peer.robot_id, now, src, challenge=True)
        if sending.send(core, replace(reply, ping=ride), src, to=to, compact=compact):
            peer.challenged_at = now
            core.counters.challenges += 1
            return
        del core._pings[ride]
    sending.send(core, reply, src, to=to, compact=compact)
    if peer is not None and not peer.proven and peer.address == src:
        challenge(core, peer, src, now)  # (the bytes did not allow it to ride)


def on_own_id(
    core: CoreState, msg: wire.Message, origin: Origin, src: Addr, seal: Sealed | None, now: float
) -> None:
    """A datagram with our robot id: our own echo, a replay, or a second daemon.  Only a
    second daemon that answers a challenge of ours (its nonce) is a conflict."""
    if isinstance(msg, Discovery) and msg.seq is not None and msg.seq in core._pings:
        # Our own challenge, sent back to us (a mirror): answering it would make our own
        # answer look like a second daemon's.
        core.counters.rejects["own"] += 1
        return
    if isinstance(msg, Response) and msg.seq is not None:
        ping = core._pings.get(msg.seq)
        if ping is not None and ping.robot_id == origin.robot_id and ping.addr == src:
            del core._pings[msg.seq]
            conflict(core, src, origin, now)  # it answered: a live second daemon
            return
    if origin.boot_id == core.boot_id and (
        seal is not None or src[0] in (core._own_host(), UNSPECIFIED)
    ):
        # Our own datagram come back (a sealed one was sealed by us, from where it came;
        # from 0.0.0.0: multicast on lo from a socket that names no source, where no other
        # robot can be, and a challenge would reach only ourselves).
        core.counters.rejects["own"] += 1
        return
    core.counters.rejects["own-claim"] += 1
    if now >= core._own_challenge_at + core.config.ping_timeout:
        # Another daemon with our id, or a forger: only a live daemon answers.
        seq = core._nonce()
        if len(core._pings) < MAX_PINGS:
            core._pings[seq] = _Ping(origin.robot_id, now, src, challenge=True)
            search = Discovery(core._origin(), core._me(), 0, seq=seq, multicast=False)
            if sending.send(core, search, src, to=origin.robot_id):
                core._own_challenge_at = now
            else:
                del core._pings[seq]
    if isinstance(msg, Discovery) and msg.seq is not None:
        # Let the other daemon find us out too.
        answer_ping(core, origin, msg.seq, src, now)


def conflict(core: CoreState, src: Addr, origin: Origin, now: float) -> None:
    core.counters.rejects["own-id"] += 1
    c = core.conflict
    if c is None:
        core.conflict = Conflict(src[0], origin.boot_id, now)
    else:
        c.address, c.boot_id, c.last_seen, c.count = src[0], origin.boot_id, now, c.count + 1
