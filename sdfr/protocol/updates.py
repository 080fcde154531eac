"""Service sets: what we announce (whole, in parts, or as a delta with the steps before
it), what we serve to one robot (its catch-up), and how a peer's set is fetched, held until
believed, assembled and applied."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

from sdfr import wire
from sdfr.protocol import challenges, sending
from sdfr.protocol.config import (
    DELTA_STEPS,
    FETCH_SETS_PER_S,
    REPAIR_MEMORY,
    UNPROVEN_BYTES,
    UNPROVEN_PARTS,
    UNPROVEN_PARTS_MIN,
    Addr,
)
from sdfr.protocol.peers import Peer, _Fetch
from sdfr.protocol.state import CoreState
from sdfr.records.model import Service, service_digest
from sdfr.wire import WANT_ALL, Discovery, Reject, Update


def want_current(core: CoreState, peer: Peer, now: float, *, soon: bool) -> None:
    """Make sure we will come to hold the set the peer announced."""
    if peer.current:
        return
    if peer.held is None and peer.digest == core._empty_digest():
        # An empty set needs no fetch.
        peer.services = ()
        peer.held = (peer.boot_id, peer.version, peer.digest)
        peer.fetch = None
        core._dirty.add(peer.robot_id)
        return
    held = peer.held_delta
    if held is not None:
        peer.held_delta = None
        o = held.origin
        if (o.boot_id, o.version, o.digest) == (peer.boot_id, peer.version, peer.digest):
            apply_delta(core, peer, held)
            if peer.current:
                return
    f = peer.fetch
    if f is not None and (f.boot_id, f.version, f.digest) == (
        peer.boot_id,
        peer.version,
        peer.digest,
    ):
        if f.parts and not f.missing():
            complete(core, peer)  # held while the set was not believed
        return  # already fetching this one
    core._drop_fetch(peer)
    peer.fetch = _Fetch(peer.boot_id, peer.version, peer.digest)
    if soon:
        peer.fetch.retry_at = now + core.config.fetch_wait
    else:
        request_fetch(core, peer, now)


def request_fetch(core: CoreState, peer: Peer, now: float) -> None:
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
            complete(core, peer)
        else:
            f.retry_at = math.inf
        return
    want: wire.Want = f.missing() if f.parts else WANT_ALL
    have = None
    if not f.parts and peer.held is not None and peer.held[0] == f.boot_id:
        # What we hold of the same boot: the answer can be what changed since.
        have = peer.held[1] if peer.held[1] < f.version else None
    sending.send(
        core,
        Discovery(
            core._origin(),
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
    f.backoff = min(core.config.beacon_interval, max(2 * f.backoff, core.config.fetch_wait * 2))
    f.retry_at = now + f.backoff * core.rng.uniform(0.8, 1.2)


def on_update(core: CoreState, peer: Peer, msg: Update, now: float) -> None:
    """A part of a set, or a delta.  A set not believed yet (its robot has not confirmed
    it in an answer to us) is held, within bounds, and applied once it is."""
    o = msg.origin
    triple = (o.boot_id, o.version, o.digest)
    believed = peer.proven and triple == (peer.boot_id, peer.version, peer.digest)
    if believed and peer.current:
        return  # a duplicate, or parts of a set we completed already
    if msg.base is not None:
        if believed:
            apply_delta(core, peer, msg)
        elif msg.packed is None or len(msg.packed) <= wire.MAX_DATAGRAM:
            peer.held_delta = msg  # (one a robot: the latest)
        return
    f = peer.fetch
    if f is None or (f.boot_id, f.version, f.digest) != triple:
        if f is not None and not believed and (f.boot_id, f.version) >= triple[:2]:
            return  # an older or competing claim than the set being assembled
        core._drop_fetch(peer)
        wait = core.config.fetch_wait if believed else math.inf
        f = peer.fetch = _Fetch(*triple, retry_at=now + wait)
    if f.parts == 0:
        f.parts = msg.parts
    elif f.parts != msg.parts:
        core.counters.rejects["inconsistent-parts"] += 1
        core._drop_fetch(peer)
        return
    if msg.part in f.got:
        return
    if not believed:
        share = max(UNPROVEN_PARTS_MIN, UNPROVEN_PARTS // max(1, core._unproven))
        size = sum(wire.service_json_size(s) for s in msg.services)
        if len(f.got) >= share or core._held_bytes + size > UNPROVEN_BYTES:
            core.counters.rejects["unproven-parts"] += 1
            return
        f.size += size
        core._held_bytes += size
    f.got[msg.part] = msg.services
    if f.missing():
        # More parts are normally right behind this one; ask only if they do not come.
        if believed:
            f.retry_at = max(f.retry_at, now + core.config.fetch_wait)
        return
    if believed:
        complete(core, peer)


def complete(core: CoreState, peer: Peer) -> None:
    """The set being assembled is whole and believed: the peer's services now."""
    f = peer.fetch
    assert f is not None
    services = tuple(s for i in range(f.parts) for s in f.got[i])
    core._drop_fetch(peer)
    if service_digest(services) != f.digest:
        core.counters.rejects["bad-digest"] += 1
        return
    peer.services = services
    peer.held = (f.boot_id, f.version, f.digest)
    core._dirty.add(peer.robot_id)


def apply_delta(core: CoreState, peer: Peer, msg: Update) -> None:
    """Turn the set we hold into the announced one, from the delta's step whose base we
    hold on (its earlier steps repair deltas we missed); without one, fetch it whole."""
    o = msg.origin
    if peer.held is None or peer.held[0] != o.boot_id:
        return
    bases = [base for base, _ in msg.steps] + [msg.base]
    if peer.held[1] not in bases:
        return
    first = bases.index(peer.held[1])
    services = peer.services
    for i in range(first, len(bases)):
        packed = (
            msg.steps[i][1].startswith(wire.PACKED)
            if i < len(msg.steps)
            else msg.packed is not None
        )
        dictionary = None
        if i == first and packed:
            # The set we hold: its dictionary is kept for the next delta from it.
            if peer.dictionary is None or peer.dictionary[0] != peer.held:
                peer.dictionary = (peer.held, wire.delta_dictionary(services))
            dictionary = peer.dictionary[1]
        if i < len(msg.steps):
            read = wire.read_step(msg.steps[i][1], services, dictionary)
        else:
            step = wire.unpack_delta(msg, services, dictionary)
            read = step if isinstance(step, Reject) else (step.services, step.removed)
        if isinstance(read, Reject):
            core.counters.rejects[read.reason] += 1
            return
        changed = {s.id: s for s in read[0]}
        gone = set(read[1])
        kept = [changed.pop(s.id, s) for s in services if s.id not in gone]
        services = (*kept, *changed.values())
    if service_digest(services) != o.digest:
        core.counters.rejects["bad-digest"] += 1
        return
    peer.services = services
    peer.held = (o.boot_id, o.version, o.digest)
    core._drop_fetch(peer)
    core._dirty.add(peer.robot_id)


def serve(
    core: CoreState,
    peer: Peer,
    dst: Addr,
    only: tuple[int, ...] | None,
    now: float,
    have: int | None = None,
) -> None:
    """Send parts of our set to `dst` by unicast, once `dst` has proven a round trip; to
    a robot that holds our set `have`, what changed since when we still know that set."""
    if not core._address_proven(dst, now):
        peer.deferred = (dst, only)
        challenges.challenge(core, peer, dst, now)
        return
    if have is not None:
        core._repair_asked = now  # it missed a delta: ours carry the steps before them
    compact = core._compact_for(dst)
    parts = update_parts(core, compact)
    catch_up = catch_up_delta(core, have, compact) if have is not None and only is None else None
    if catch_up is not None and parts:
        # One datagram, no bigger than a part: it costs the budget one part.
        if not core._fetch_budget.take(dst[0], now, 1 / (FETCH_SETS_PER_S * len(parts))):
            core.counters.rejects["fetch-limited"] += 1
            return
        sending.emit(core, catch_up, dst, "update", to=peer.robot_id)
        return
    if only is not None and any(i >= len(parts) for i in only):
        only = None  # numbered in another form of the set: send it whole
    wanted = len(parts) if only is None else len(only)
    # Per address, at most FETCH_SETS_PER_S whole sets a second.
    if not parts or not core._fetch_budget.take(
        dst[0], now, wanted / (FETCH_SETS_PER_S * len(parts))
    ):
        core.counters.rejects["fetch-limited"] += 1
        return
    send_update_parts(core, dst, now, only=only, to=peer.robot_id)


def flush_replies(core: CoreState, now: float) -> None:
    """Answer the searches gathered during the reply delay: one multicast serves many.

    A lone searcher gets the set by unicast (once its address has answered a ping of
    ours); several by multicast, at most once every `mcast_set_gap` (a multicast is aimed
    at nobody, and a flood of searches costs one set a gap).
    """
    targets = core._reply_to
    if len(targets) == 1:
        ((dst, robot_id),) = targets.items()
        core._reply_to, core._reply_at = {}, math.inf
        peer = core.peers.get(robot_id)
        if peer is not None:
            serve(core, peer, dst, None, now)
        return
    gap = core.config.mcast_set_gap
    if now < core._last_set_multicast + gap:
        core._reply_at = core._last_set_multicast + gap
        return
    core._reply_to, core._reply_at = {}, math.inf
    if targets:
        send_update_parts(core, None, now)


def announce(core: CoreState, now: float) -> None:
    """The local set is announced now: from here on it is what we tell of."""
    core._announced = (core.version, core.services, core.digest)
    core._recent[core.version] = core.services
    core._recent.move_to_end(core.version)
    while len(core._recent) > max(1, core.config.delta_history):
        core._recent.popitem(last=False)
    core._update_budget.take(now)  # (an announcement that found none saved spends none)
    core._update_at = math.inf
    core._steps = []  # a delta sent now puts its own step back (`announce_change`)


def update_parts(core: CoreState, compact: bool = False) -> list[bytes]:
    """The set we tell of (`_advertised`), in parts."""
    version, services, digest = core._advertised()
    key = (core.boot_id, version, digest, core.location, compact)
    if core._parts_cache is None or core._parts_cache[0] != key:
        try:
            parts = wire.encode_update_parts(
                core._origin(),
                core.location,
                core.config.max_age,
                services,
                group=core.config.group,
                port=core.config.port,
                compact=compact,
            )
            core.announce_error = None
        except ValueError as exc:
            # Nothing a peer could assemble: announce nothing (the beacons still go out)
            # and say why, rather than stop.  The API refuses sets this large.
            parts = []
            core.announce_error = f"cannot announce the service set: {exc}"
        core._parts_cache = (key, parts)
    return core._parts_cache[1]


def announce_change(core: CoreState, now: float) -> None:
    """Multicast what changed since the last announcement: a delta when it is smaller.

    While peers lately asked for catch-ups, the delta also carries the steps of the
    deltas just before it (`REPAIR_MEMORY`), so that a robot that missed them catches up
    from this one datagram rather than by asking."""
    prev = core._announced
    if prev is None or prev[0] >= core.version:
        send_update_parts(core, None, now)
        return
    history = core._steps
    chained = history if history and history[-1][1] == prev[0] else []
    steps = chained if now - core._repair_asked <= REPAIR_MEMORY else []
    announce(core, now)
    compact = core._compact_for(None)
    data = delta(core, prev[0], prev[1], compact, [(b, body) for b, _, body in steps])
    if data is None:  # too large for one datagram, or no smaller than the whole set
        send_update_parts(core, None, now)
        return
    if compact and DELTA_STEPS > 1:
        own = (prev[0], core.version, wire.last_step(data))
        core._steps = [*chained, own][1 - DELTA_STEPS :]
    sending.emit(core, data, None, "update")


def delta(
    core: CoreState,
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
    _, services, _ = core._advertised()
    new_ids = {s.id for s in services}
    added = tuple(s for s in services if old.get(s.id) != s)
    if services and len(added) == len(services):
        return None
    removed = tuple(sid for sid in old if sid not in new_ids)
    location, max_age = ("", 0) if compact else (core.location, core.config.max_age)
    delta = Update(core._origin(), location, max_age, 0, 1, added, base=base, removed=removed)
    cfg = core.config
    # Compact: deflated against the base set, which every robot that can apply it holds.
    dictionary = own_dictionary(core, base, had) if compact else None
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


def own_dictionary(core: CoreState, version: int, services: tuple[Service, ...]) -> bytes:
    """`wire.delta_dictionary` of our set `version`, kept for the next delta from it."""
    if core._dictionary_cache is None or core._dictionary_cache[0] != version:
        core._dictionary_cache = (version, wire.delta_dictionary(services))
    return core._dictionary_cache[1]


def catch_up_delta(core: CoreState, have: int, compact: bool) -> bytes | None:
    """What changed since our set `have`, for a robot that holds it (None: we no longer
    know that set, or the whole set is as small)."""
    version, _, _ = core._advertised()
    had = core._recent.get(have)
    if had is None or have >= version:
        return None
    return delta(core, have, had, compact)


def send_update_parts(
    core: CoreState,
    dst: Addr | None,
    now: float,
    only: Sequence[int] | None = None,
    to: str | None = None,
) -> None:
    if dst is None:
        # A multicast set answers every pending search too.
        core._reply_to.clear()
        core._reply_at = math.inf
        announce(core, now)
        core._last_set_multicast = now
    parts = update_parts(core, core._compact_for(dst))
    for i, data in enumerate(parts):
        if only is None or i in only:
            sending.emit(core, data, dst, "update", to=to)
