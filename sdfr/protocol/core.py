"""The protocol core: what arrives, whom to trust, and the public entry points."""

from __future__ import annotations

import ipaddress
import math
from collections.abc import Iterable, Sequence
from dataclasses import replace
from urllib.parse import urlsplit

from sdfr import auth, wire
from sdfr.auth import Keyring, Sealed
from sdfr.model import PeerRecord, Service, service_digest
from sdfr.protocol.config import (
    CHALLENGE_PAD,
    CHALLENGE_RATE,
    FETCH_SETS_PER_S,
    MAX_PEERS,
    MAX_PINGS,
    MAX_REPLY_TO,
    MAX_UNPROVEN,
    UNPROVEN_BYTES,
    UNPROVEN_PARTS,
    UNPROVEN_PARTS_MIN,
    Addr,
    Outgoing,
    answers_beacon,
)
from sdfr.protocol.peers import Conflict, Peer, _Fetch, _Ping
from sdfr.protocol.state import CoreState
from sdfr.wire import (
    WANT_ALL,
    WIRE_COMPACT,
    Alive,
    Byebye,
    Discovery,
    Origin,
    Reject,
    Response,
    Update,
)

_KIND = {Discovery: "discovery", Response: "response", Update: "update", Alive: "alive"}
#: The source of a datagram sent from no address (see `_on_own_id`).
UNSPECIFIED = "0.0.0.0"
#: A peer's smoothed RTT is stored (and listed) again once it moved from the stored one by more
#: than this share of it and this many seconds: a true figure without a write per round trip.
RTT_TELL_SHARE = 0.2
RTT_TELL_S = 0.002
#: A reachable peer whose answers stop coming is pinged once every 1/REPROVE_PINGS of its proof
#: window over the last two thirds of it (16 pings): the chance that a live robot on a link
#: losing 30 % each way misses them all is 0.51 ** 16, about one in 50,000.
REPROVE_PINGS = 24


class Core(CoreState):
    """One robot's discovery protocol."""

    # -- life cycle ------------------------------------------------------------------------

    @property
    def started(self) -> bool:
        return self._started

    def start(self, now: float) -> None:
        """Announce ourselves and ask who is there."""
        self._now = now
        self._started = True
        self._search(now)
        self._send_update_parts(None, now)
        # A second search covers a lost first one; beacons cover the rest.
        self._discovery_repeat = now + self.config.reply_delay_max + self.rng.uniform(0.2, 0.5)
        self._next_beacon = now + self._beacon_period()
        self._next_prune = now + self.config.proven_for

    def stop(self, now: float) -> None:
        """Say goodbye; nothing is sent after this."""
        if self._started and not self._stopped:
            self._send(Byebye(self._origin()), None)
        self._stopped = True

    # -- inputs ----------------------------------------------------------------------------

    def set_subnet(self, subnet: str | None) -> None:
        """Our own subnet ("10.1.0.0/16"): plain SSDP searches from elsewhere are not answered.
        Without one, our address's /24 (or /64) stands in."""
        self.subnet = None if subnet is None else ipaddress.ip_network(subnet, strict=False)

    def set_keyring(self, keyring: Keyring) -> None:
        """The fleet keyring changed (a key installed, put to use or removed; the mode)."""
        self.keyring = keyring

    def set_location(self, location: str, now: float | None = None) -> None:
        """Our address (so LOCATION) changed; with `now`, tell the fleet at once."""
        if now is not None:
            self._now = now
        self.location = location
        self._parts_cache = None
        if now is not None and self._started and not self._stopped:
            # Peers key us by robot id and take the new address from this datagram.
            self._send(Alive(self._origin(), self.location, self.config.max_age), None)
            # Questions asked from the old address (say, one that another robot also held)
            # may have gone nowhere: ask again now rather than after their back-off.
            for peer in self.peers.values():
                if peer.fetch is not None:
                    peer.fetch.backoff = 0.0
                    peer.fetch.retry_at = now

    def set_services(self, version: int, services: Sequence[Service], now: float) -> None:
        """The local registrations changed: announce the new set (coalescing bursts)."""
        if version == self.version and tuple(services) == self.services:
            return
        self.version = version
        self.services = tuple(services)
        self.digest = service_digest(self.services)
        if self._started and not self._stopped:
            # After a quiet spell at once (a burst from one program gathers for
            # `update_coalesce`); within `update_gap` of the last change announced, at its end.
            cfg = self.config
            due = max(now + cfg.update_coalesce, self._last_change_sent + cfg.update_gap)
            self._update_at = min(self._update_at, due)

    def restore(self, views: Iterable[PeerRecord]) -> None:
        """Load the history map saved by an earlier run: every peer starts unreachable and
        unproven (what it said in an earlier run of ours proves nothing now), and is listed
        again once it answers a ping of this run."""
        for v in views:
            if v.robot_id == self.config.robot_id:
                continue
            held = (
                (v.boot_id, v.version, v.digest) if service_digest(v.services) == v.digest else None
            )
            self.peers[v.robot_id] = Peer(
                robot_id=v.robot_id,
                address=(v.address, self.config.port),
                location=v.location,
                first_seen=v.first_seen,
                last_heard=v.last_seen,
                boot_id=v.boot_id,
                version=v.version,
                digest=v.digest,
                reachable=False,
                proven=False,
                known=True,  # only robots proven once are saved
                held=held,
                services=v.services if held else (),
                rtt=None if v.rtt_ms is None else v.rtt_ms / 1000,
            )

    def receive(self, data: bytes, src: Addr, now: float) -> None:
        """A datagram arrived from `src`."""
        self._now = now
        self.counters.bytes_in += len(data)
        if not self._sources.take(src[0], now):
            self.counters.rejects["rate-limited"] += 1
            return
        self._credit.earn(src[0], len(data))
        seal = auth.check(data, self.keyring, me=self.config.robot_id, src=src[0])
        if isinstance(seal, Reject):
            if seal.reason == "unsigned" and self._plain_search_allowed(data):
                seal = None  # a plain SSDP client's search: read-only, answered below
            else:
                self.counters.rejects[seal.reason] += 1
                return
        msg = wire.decode(data, fleet=self.config.fleet)
        if isinstance(msg, Reject):
            self.counters.rejects[msg.reason] += 1
            return
        if self._stopped:
            return
        self.counters.datagrams_in[_KIND.get(type(msg), "byebye")] += 1
        if seal is not None:
            self.counters.verified[seal.kid] += 1
        if isinstance(msg, Discovery) and msg.st not in self._targets():
            self.counters.rejects["other-target"] += 1
            return
        if isinstance(msg, Discovery) and msg.origin is None:
            self._on_plain_search(msg, src, now)
            return
        origin = msg.origin
        assert origin is not None
        if origin.robot_id == self.config.robot_id:
            self._on_own_id(msg, origin, src, seal, now)
            return
        if isinstance(msg, Byebye):
            known = self.peers.get(origin.robot_id)
            if known is None or not known.proven:
                if known is not None and not known.known:
                    self._forget(known)
                return  # a robot we never proved leaves: nothing to believe, nothing to ask
        proof = self._take_proof(msg, origin, src, now)
        ping = isinstance(msg, Discovery) and msg.seq is not None
        peer, believed = self._gate(origin, src, now, seal, proof, ping=ping)
        if isinstance(msg, Discovery):
            self._on_discovery(msg, peer if believed else None, src, now, answer_ping=True)
            if peer is not None and not believed and isinstance(msg.want, str):
                self._remember_search(msg, peer, src, now)
            return
        if peer is None:
            return
        if isinstance(msg, Update):
            # Held until its set is believed (an answer confirms it), applied at once if it is.
            self._on_update(peer, msg, now)
        if not believed:
            if isinstance(msg, Response) and msg.ping is not None and msg.seq is not None:
                self._answer_ping(origin, msg.ping, src, now)  # let it prove us in turn
            return
        if isinstance(msg, Byebye):
            self._on_byebye(peer)
            return
        self._heard(peer, origin, src, now, getattr(msg, "location", None), proof)
        if isinstance(msg, Response):
            self._on_response(peer, msg, src, now, proof)
        elif (
            isinstance(msg, Alive)
            and msg.seq is not None
            and answers_beacon(self.config.robot_id, msg.seq, msg.turns)
        ):
            # A beacon that is a ping to all who hear it (or to those whose turn it is):
            # answer it (the compact ping reply).
            self._answer_ping(origin, msg.seq, src, now)
        if peer.robot_id in self.peers and peer.proven:
            # More parts of a whole set are normally right behind this one; a delta we
            # could not apply will not be followed by anything that helps.
            soon = isinstance(msg, Update) and msg.base is None
            self._want_current(peer, now, soon=soon)

    def handle_timer(self, now: float) -> None:
        """Do whatever is due at `now`."""
        if not self._started or self._stopped:
            return
        self._now = now
        cfg = self.config
        if now >= self._discovery_repeat:
            self._discovery_repeat = math.inf
            self._search(now)
        if now >= self._update_at:
            self._update_at = math.inf
            self._announce_change(now)
        if now >= self._reply_at:
            self._flush_replies(now)
        if now >= self._next_beacon:
            self._beacon(now)
            self._next_beacon = now + self._beacon_period()
        if now >= self._next_prune:
            self._prune(now)
        expired = [seq for seq, p in self._pings.items() if now >= p.sent + cfg.ping_timeout]
        for seq in expired:
            ping = self._pings.pop(seq)
            peer = self.peers.get(ping.robot_id)
            if peer is not None and ping.addr == peer.address and peer.proven:
                # (A challenge to another address, or to a robot not proven yet, says nothing
                # of the peer's link.)
                self._settle_ping(peer, ok=False)
        late = [s for s, g in self._group_pings.items() if now >= g.sent + cfg.ping_timeout]
        for seq in late:
            for robot_id, addr in self._group_pings.pop(seq).targets.items():
                peer = self.peers.get(robot_id)
                if peer is not None and addr == peer.address:
                    self._settle_ping(peer, ok=False)
        if self.conflict is not None and now >= self.conflict.last_seen + cfg.dead_after:
            self.conflict = None  # no second daemon has answered for a miss window
        window = cfg.proof_window(self._turns)
        for peer in list(self.peers.values()):
            if not peer.known and now >= peer.last_heard + cfg.dead_after:
                self._forget(peer)
                continue
            if peer.reachable and (
                now >= peer.answered_at + window or now >= peer.last_heard + cfg.dead_after
            ):
                # Silent for the miss limit, or no answer to our pings for a miss window:
                # whatever else arrives in its name (a replay, a relay, a late datagram) does
                # not keep it listed.
                peer.reachable = False
                peer.next_ping = math.inf
                self._drop_fetch(peer)
                self._dirty.add(peer.robot_id)
                continue
            if not peer.proven and now >= peer.next_ping:
                if now < peer.claimed_at + cfg.dead_after:
                    self._challenge(peer, peer.address, now)
                    peer.next_ping = max(peer.next_ping, now + 1.0 / CHALLENGE_RATE)
                else:
                    peer.next_ping = math.inf
            elif self._doubted(peer, now):
                # A claim it has not confirmed yet, whose challenge had to wait (one had just
                # been answered): ask now.
                addr = peer.claim_addr or peer.address
                if not self._challenge(peer, addr, now, pad=not peer.reachable):
                    peer.challenged_at = now  # (no budget or bytes for it: a timeout later)
            elif peer.reachable and now >= peer.next_ping:
                self._ping(peer, now)
            elif peer.reachable and now >= self._reprove_at(peer, window):
                # Its answers went missing lately (a lossy link): ask it alone, REPROVE_PINGS
                # times in what is left of its window, so that only a robot really gone (or
                # a link really down) runs out of it.
                peer.challenged_at = now
                if self._challenge_budget.take(now):
                    self._ping(peer, now, challenge=True)
            if peer.fetch is not None and now >= peer.fetch.retry_at:
                self._request_fetch(peer, now)

    def next_deadline(self) -> float | None:
        """When `handle_timer` must run next (None: only an input can change anything)."""
        if not self._started or self._stopped:
            return None
        cfg = self.config
        t = min(
            self._next_beacon,
            self._discovery_repeat,
            self._update_at,
            self._reply_at,
            self._next_prune,
        )
        for ping in self._pings.values():
            t = min(t, ping.sent + cfg.ping_timeout)
        for group in self._group_pings.values():
            t = min(t, group.sent + cfg.ping_timeout)
        if self.conflict is not None:
            t = min(t, self.conflict.last_seen + cfg.dead_after)
        window = cfg.proof_window(self._turns)
        for peer in self.peers.values():
            if peer.reachable:
                t = min(
                    t,
                    peer.answered_at + window,
                    peer.last_heard + cfg.dead_after,
                    peer.next_ping,
                    self._reprove_at(peer, window),
                )
            elif not peer.proven:
                t = min(t, peer.next_ping)
            retry = peer.challenged_at + cfg.ping_timeout
            if (
                peer.proven
                and peer.answered_at < peer.claimed_at
                and retry < (peer.claimed_at + cfg.dead_after)
            ):
                t = min(t, retry)  # (`_doubted`)
            if not peer.known:
                t = min(t, peer.last_heard + cfg.dead_after)
            if peer.fetch is not None:
                t = min(t, peer.fetch.retry_at)
        return None if t == math.inf else t

    # -- outputs ---------------------------------------------------------------------------

    def datagrams_to_send(self) -> list[Outgoing]:
        out, self._out = self._out, []
        return out

    def round_trip_proven(self, addr: Addr, now: float) -> bool:
        """Whether a ping to `addr` was answered within the last two ping intervals: what
        goes there now can tell the kernel the neighbour is reachable (``MSG_CONFIRM``), so
        it does not probe it with ARP while the pings keep coming back."""
        t = self._answered.get(addr)
        return t is not None and now - t <= 2 * self.config.ping_interval

    @property
    def has_dirty(self) -> bool:
        return bool(self._dirty) or bool(self._removed)

    def take_dirty(self) -> list[PeerRecord]:
        """Proven peers whose stored view changed since the last call."""
        views = []
        for r in sorted(self._dirty):
            peer = self.peers.get(r)
            if peer is not None and peer.known:
                peer.rtt_told = peer.rtt
                views.append(self.view(peer))
        self._dirty.clear()
        return views

    def mark_unsaved(self, robot_ids: Iterable[str], removed: Iterable[str]) -> None:
        """Views taken but not saved (the disk was full): give them back for the next save."""
        self._dirty.update(r for r in robot_ids if r in self.peers)
        self._removed.update(removed)

    def take_removed(self) -> list[str]:
        """Robots forgotten since the last call (the history map was full): unsave them."""
        removed = sorted(self._removed)
        self._removed.clear()
        return removed

    def view(self, peer: Peer) -> PeerRecord:
        return PeerRecord(
            robot_id=peer.robot_id,
            address=peer.address[0],
            location=peer.location,
            boot_id=peer.boot_id,
            version=peer.version,
            digest=peer.digest,
            reachable=peer.reachable,
            first_seen=peer.first_seen,
            last_seen=peer.last_heard,
            indicator=peer.indicator,
            rtt_ms=None if peer.rtt is None else round(peer.rtt * 1000, 3),
            pings=len(peer.pings),
            services=peer.services,
            departed=peer.byebye_boot == peer.boot_id,
        )

    def reachable(self) -> list[str]:
        """Robots reachable now and proven (those a robot lists)."""
        return sorted(r for r, p in self.peers.items() if p.reachable and p.proven)

    @property
    def ssdp_interop(self) -> bool:
        return auth.plain_ssdp_answered(self.config.ssdp_interop, self.keyring)

    # -- trust -----------------------------------------------------------------------------

    def _gate(
        self,
        origin: Origin,
        src: Addr,
        now: float,
        seal: Sealed | None,
        proof: bool,
        *,
        ping: bool = False,
    ) -> tuple[Peer | None, bool]:
        """The peer a datagram speaks for (None: refused), and whether what it says may be
        believed now.

        Only a peer's answer to a ping of ours (`proof`: its nonce makes it fresh) changes
        what we believe of it: its boot, version, digest and address.  Anything else from a
        robot not proven in this run, of another boot or from another address is not believed
        but answered with a challenge; its Update parts may be held until the answer comes.
        A sealed datagram whose counter was seen already in the proven boot is a replay.
        """
        peer = self.peers.get(origin.robot_id)
        if peer is None:
            refused = self._admit(now)
            if refused is not None:
                return self._refuse(refused)
            peer = self.peers[origin.robot_id] = Peer(
                robot_id=origin.robot_id,
                address=src,
                location="",
                first_seen=now,
                last_heard=now,
                boot_id=origin.boot_id,
                version=origin.version,
                digest=origin.digest,
            )
            self._unproven += 1
        if proof:
            self._prove(peer, origin, src, now)
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
            self.counters.rejects["unproven"] += 1
            peer.claimed_at = now
            if not peer.known:  # (a robot of the history map keeps its record as it was)
                peer.last_heard = now
                peer.address = src
                peer.wire = origin.wire  # (only the form of what we send it)
            if not ping:  # (a ping's answer carries our challenge: `_answer_ping`)
                self._challenge(peer, src, now)
            return peer, False
        if seal is not None and origin.boot_id == peer.boot_id:
            if not peer.window.fresh(origin.boot_id, seal.counter):
                return self._refuse("replay")
            peer.window.accept(origin.boot_id, seal.counter)
        if src != peer.address:
            # A robot moves only to where it answers a challenge: a datagram sent again
            # from elsewhere must not move it (nor bring a dead one back there).  (A listed
            # robot that moved knows us: its answer needs no room for a challenge of ours.)
            self._doubt(peer, src, now, pad=not peer.reachable)
            self._refuse("other-address")
            return peer, False
        if origin.boot_id != peer.boot_id:
            # A new boot, an earlier life's datagram (late or replayed), or a robot that lost
            # its state (and its clock): only its answer to a challenge tells.  (A newer boot
            # is asked at once: a challenge still in flight went to its dead predecessor.)
            self._doubt(peer, src, now, urgent=origin.boot_id > peer.boot_id)
            self._refuse("stale-boot" if origin.boot_id < peer.boot_id else "unproven")
            return peer, False
        if peer.byebye_boot == origin.boot_id:
            # After a Byebye only an answer to our challenge brings that boot back (a Byebye
            # anyone could have sent must not lock a robot out).
            self._doubt(peer, src, now)
            self._refuse("after-byebye")
            return peer, False
        return peer, True

    def _refuse(self, reason: str) -> tuple[None, bool]:
        self.counters.rejects[reason] += 1
        return None, False

    def _admit(self, now: float) -> str | None:
        """Make room for a new robot; the reason it cannot have any, else None."""
        if self._unproven >= MAX_UNPROVEN:
            return "unproven-full"
        if len(self.peers) < MAX_PEERS:
            return None
        gone = [p for p in self.peers.values() if not p.reachable]
        if not gone:
            return "peers-full"
        oldest = min(gone, key=lambda p: p.last_heard)
        self._forget(oldest)
        if oldest.known:
            self._removed.add(oldest.robot_id)
        return None

    def _forget(self, peer: Peer) -> None:
        del self.peers[peer.robot_id]
        self._drop_fetch(peer)
        if not peer.known:
            self._unproven -= 1
        self._dirty.discard(peer.robot_id)
        for seq in [s for s, p in self._pings.items() if p.robot_id == peer.robot_id]:
            del self._pings[seq]

    def _doubted(self, peer: Peer, now: float) -> bool:
        """Whether a proven peer said something we have not seen it confirm, and may be
        challenged about it now."""
        return (
            peer.proven
            and peer.answered_at < peer.claimed_at
            and now < peer.claimed_at + self.config.dead_after
            and now >= peer.challenged_at + self.config.ping_timeout
        )

    def _doubt(
        self, peer: Peer, src: Addr, now: float, *, pad: bool = True, urgent: bool = False
    ) -> None:
        """A claim of `peer`'s we do not believe on its word: challenge it (at `src`), now or
        as soon as its last challenge allows (`_doubted`); `urgent`: CHALLENGE_GAP after it."""
        peer.claimed_at = now
        peer.claim_addr = src
        if urgent:
            self._challenge_soon(peer, now)
        self._challenge(peer, src, now, pad=pad)

    def _reprove_at(self, peer: Peer, window: float) -> float:
        """When a reachable peer whose answers went missing is pinged again."""
        return max(peer.answered_at + window / 3, peer.challenged_at + window / REPROVE_PINGS)

    def _take_proof(self, msg: wire.Message, origin: Origin, src: Addr, now: float) -> bool:
        """Whether `msg` answers a ping of ours (its nonce) from where the ping went; the ping
        is settled (used up) only then, so a forgery cannot take it away."""
        if not isinstance(msg, Response) or msg.seq is None:
            return False
        ping = self._pings.get(msg.seq)
        if ping is not None:
            if ping.robot_id != origin.robot_id or ping.addr != src:
                return False
            del self._pings[msg.seq]
            peer = self.peers.get(origin.robot_id)
            if peer is not None:
                if ping.addr == peer.address or not peer.proven:
                    self._round_trip(peer, now - ping.sent, src, now)
                else:
                    self._answered[src] = now
            return self._newest_answer(peer, ping.sent)
        group = self._group_pings.get(msg.seq)
        group = self._group_pings.get(msg.seq)
        if group is None or origin.robot_id in group.heard:
            return False
        peer = self.peers.get(origin.robot_id)
        expected = group.targets.get(origin.robot_id)
        if expected is not None:
            if expected != src:
                return False
            del group.targets[origin.robot_id]
        elif peer is None or peer.address != src:
            return False  # (a robot we do not know joins by its search and our challenge)
        group.heard.add(origin.robot_id)
        if peer is not None:
            self._round_trip(peer, now - group.sent, src, now)
        return self._newest_answer(peer, group.sent)

    @staticmethod
    def _newest_answer(peer: Peer | None, asked: float) -> bool:
        """Whether an answer to a ping sent at `asked` may be believed: not when an answer to
        a later ping was believed already (a late answer of an earlier life, held back by the
        network or an outsider, must not undo what its successor said)."""
        if peer is None:
            return True
        if asked < peer.asked_at:
            return False
        peer.asked_at = asked
        return True

    def _challenge(self, peer: Peer, addr: Addr, now: float, *, pad: bool = True) -> bool:
        """Ping `peer` at `addr` so that its answer settles a claim; False if none was sent.
        `pad` (CHALLENGE_PAD): the robot there may not have proven us (it is new, restarted,
        moved, or we were apart): the challenge pays for its answer with its own challenge
        riding on it, which it sends no unproven address more bytes than it got from there.

        One at a time per robot, at most one a ping timeout; per address and in all at most
        ADDR_CHALLENGE_RATE and CHALLENGE_RATE; and to an address that has not proven a round
        trip, no more bytes than it sent (`_emit`): a flood of claims costs a bounded trickle.
        """
        if now < peer.challenged_at + self.config.ping_timeout:
            return True  # one is in flight (or was just answered)
        if not self._address_proven(addr, now) and not self._addr_challenges.take(addr[0], now):
            self.counters.challenges_limited += 1
            return False
        if not self._challenge_budget.take(now):
            self.counters.challenges_limited += 1
            if not peer.proven:  # try again as soon as the budget allows
                peer.next_ping = min(peer.next_ping, now + 1.0 / CHALLENGE_RATE)
            return False
        if not self._ping(peer, now, addr=addr, challenge=True, pad=pad):
            if len(self._pings) < MAX_PINGS and not self._address_proven(addr, now):
                self._invite(now)  # (its address has not paid for the challenge yet)
            return False
        peer.challenged_at = now
        self.counters.challenges += 1
        return True

    def _invite(self, now: float) -> None:
        """Ask every robot that has not proven us to challenge us: an extra beacon, without a
        nonce, padded so that the challenge it draws (padded itself, `CHALLENGE_PAD`) costs
        no more than it brings.  Sent when a robot's first beacon does not pay for our
        challenge of it: the two meet within one round trip of the first beacon heard, not a
        beacon period later.  Robots that believe us take it as the beacon it is.  At most
        one a beacon period: a multicast is sent to no third party, and claims cost the group
        one datagram a period at most."""
        if not self._invites.take(now):
            return
        compact = self._compact_for(None)
        me = self._origin()
        # (In the beacon's own form: the compact one names no LOCATION, no max-age.)
        invite = Alive(me, "", 0) if compact else Alive(me, self.location, self.config.max_age)
        # The largest challenge a robot that has not proven us sends back: its id may be
        # longer than ours, its boot, version and nonce as long as they go.
        longest = max((len(p.robot_id) for p in self.peers.values() if not p.proven), default=0)
        them = replace(
            me,
            robot_id="x" * max(longest, len(me.robot_id)),
            boot_id=2**31 - 1,
            version=max(me.version, 10**6),
        )
        challenge = Discovery(them, self._me(), 0, seq=wire.MAX_SEQ, multicast=False)
        group, port = self.config.group, self.config.port
        size = len(wire.encode(invite, group=group, port=port, compact=compact))
        # (A unicast search names the robot's address: as long as an address goes.)
        far = "fe80::ffff:ffff:ffff:ffff" if ":" in group else "255.255.255.255"
        need = len(wire.encode(challenge, group=far, port=port, compact=compact))
        need += CHALLENGE_PAD + len(me.robot_id)  # (its seal names us, ours the fleet)
        if self._send(invite, None, compact=compact, pad=need - size):
            self.counters.invites += 1

    def _address_proven(self, addr: Addr, now: float) -> bool:
        """Whether `addr` answered a ping of ours lately: it may get more than it sent."""
        t = self._answered.get(addr)
        return t is not None and now - t <= self.config.proven_for

    def _prune(self, now: float) -> None:
        horizon = now - self.config.proven_for
        for addr in [a for a, t in self._answered.items() if t < horizon]:
            del self._answered[addr]
        self._wire_at = {p.address: p.wire for p in self.peers.values()}
        # What unbelieved sets hold, counted again (the running count is only bookkeeping).
        self._held_bytes = sum(p.fetch.size for p in self.peers.values() if p.fetch is not None)
        self._next_prune = now + self.config.proven_for

    def _plain_search_allowed(self, data: bytes) -> bool:
        """An unsigned plain SSDP search in a keyed fleet, which ssdp_interop may answer."""
        # (No X-SDFR header of any form: a compact search's origin is its X-SDFR line.)
        return self.ssdp_interop and data.startswith(b"M-SEARCH ") and b"X-SDFR" not in data

    def _on_plain_search(self, msg: Discovery, src: Addr, now: float) -> None:
        """A plain SSDP client: its one standard search response, read-only, only on our own
        subnet, and rate-limited per source and in all (the answer is larger than the search:
        no more than that to an address that may be a spoofed victim's)."""
        cfg = self.config
        if not self.ssdp_interop:
            self.counters.rejects["ssdp-interop-off"] += 1
            return
        if not self._on_subnet(src[0]):
            self.counters.rejects["off-subnet"] += 1
            return
        if not self._plain_sources.take(src[0], now) or not self._plain_budget.take(now):
            self.counters.rejects["rate-limited"] += 1
            return
        answer = Response(self._origin(), msg.st, self.location, cfg.max_age)
        self._send(answer, src, compact=False, answer=True)  # a standard client: the full form

    def _on_subnet(self, host: str) -> bool:
        """Whether `host` is on our own subnet (`subnet`; without one, our address's /24)."""
        try:
            addr = ipaddress.ip_address(auth.host_of(host))
            if self.subnet is not None:
                return addr in self.subnet
            own = self._own_host()
            if own is None:
                return False
            prefix = 24 if addr.version == 4 else 64
            return addr in ipaddress.ip_network(f"{auth.host_of(own)}/{prefix}", strict=False)
        except ValueError:
            return False

    def _on_own_id(
        self, msg: wire.Message, origin: Origin, src: Addr, seal: Sealed | None, now: float
    ) -> None:
        """A datagram with our robot id: our own echo, a replay, or a second daemon.  Only a
        second daemon that answers a challenge of ours (its nonce) is a conflict."""
        if isinstance(msg, Discovery) and msg.seq is not None and msg.seq in self._pings:
            # Our own challenge, sent back to us (a mirror): answering it would make our own
            # answer look like a second daemon's.
            self.counters.rejects["own"] += 1
            return
        if isinstance(msg, Response) and msg.seq is not None:
            ping = self._pings.get(msg.seq)
            if ping is not None and ping.robot_id == origin.robot_id and ping.addr == src:
                del self._pings[msg.seq]
                self._conflict(src, origin, now)  # it answered: a live second daemon
                return
        if origin.boot_id == self.boot_id and (
            seal is not None or src[0] in (self._own_host(), UNSPECIFIED)
        ):
            # Our own datagram come back (a sealed one was sealed by us, from where it came;
            # from 0.0.0.0: multicast on lo from a socket that names no source, where no other
            # robot can be, and a challenge would reach only ourselves).
            self.counters.rejects["own"] += 1
            return
        self.counters.rejects["own-claim"] += 1
        if now >= self._own_challenge_at + self.config.ping_timeout:
            # Another daemon with our id, or a forger: only a live daemon answers.
            seq = self._nonce()
            if len(self._pings) < MAX_PINGS:
                self._pings[seq] = _Ping(origin.robot_id, now, src, challenge=True)
                search = Discovery(self._origin(), self._me(), 0, seq=seq, multicast=False)
                if self._send(search, src, to=origin.robot_id):
                    self._own_challenge_at = now
                else:
                    del self._pings[seq]
        if isinstance(msg, Discovery) and msg.seq is not None:
            # Let the other daemon find us out too.
            self._answer_ping(origin, msg.seq, src, now)

    def _conflict(self, src: Addr, origin: Origin, now: float) -> None:
        self.counters.rejects["own-id"] += 1
        c = self.conflict
        if c is None:
            self.conflict = Conflict(src[0], origin.boot_id, now)
        else:
            c.address, c.boot_id, c.last_seen, c.count = src[0], origin.boot_id, now, c.count + 1

    def _own_host(self) -> str | None:
        try:
            return urlsplit(self.location).hostname
        except ValueError:
            return None

    def _answer_ping(self, origin: Origin | None, seq: int, src: Addr, now: float) -> None:
        """The compact ping reply to `seq`, for the robot that pinged (from `src`); to a robot
        we have not proven, our own challenge rides on it when the bytes allow."""
        to = None if origin is None else origin.robot_id
        peer = None if to is None else self.peers.get(to)
        reply = Response(self._origin(), self._me(), "", 0, seq)
        # (The form its ping says it reads: the smallest answer.)
        compact = self.config.wire_compact and origin is not None and origin.wire >= WIRE_COMPACT
        if (
            peer is not None
            and (not peer.proven or not peer.reachable)
            and peer.address == src
            and now >= peer.challenged_at + self.config.ping_timeout
            and len(self._pings) < MAX_PINGS
        ):
            ride = self._nonce()
            self._pings[ride] = _Ping(peer.robot_id, now, src, challenge=True)
            if self._send(replace(reply, ping=ride), src, to=to, compact=compact):
                peer.challenged_at = now
                self.counters.challenges += 1
                return
            del self._pings[ride]
        self._send(reply, src, to=to, compact=compact)
        if peer is not None and not peer.proven and peer.address == src:
            self._challenge(peer, src, now)  # (the bytes did not allow it to ride)

    def _remember_search(self, msg: Discovery, peer: Peer, src: Addr, now: float) -> None:
        """A search from a robot not believed yet: served (by unicast) once it answers."""
        if not msg.multicast:
            peer.deferred = (src, None if msg.want == WANT_ALL else msg.want)
        elif len(self._reply_to) < MAX_REPLY_TO:
            self._reply_to[src] = peer.robot_id
            delay = self.rng.uniform(0, min(float(msg.mx), self.config.reply_delay_max))
            self._reply_at = min(self._reply_at, now + delay)

    # -- message handlers ------------------------------------------------------------------

    def _targets(self) -> set[str]:
        cfg = self.config
        return {"ssdp:all", wire.DEVICE_TYPE, wire.fleet_target(cfg.fleet), self._me()}

    def _me(self) -> str:
        return f"uuid:{self.config.robot_id}"

    def _on_discovery(
        self, msg: Discovery, peer: Peer | None, src: Addr, now: float, *, answer_ping: bool
    ) -> None:
        cfg = self.config
        if peer is not None:
            self._heard(peer, msg.origin, src, now, None, False)
        if msg.seq is not None and answer_ping:
            # A ping (anyone's: a robot whose claims we doubt must still be able to prove us),
            # if it names us: the compact reply, carrying our own ping to that peer when it
            # would be due within half a ping interval.
            if msg.st != self._me():
                self.counters.rejects["other-target"] += 1
            elif (
                peer is not None
                and peer.reachable
                and peer.proven
                and peer.address == src
                and peer.next_ping - now <= cfg.ping_interval / 2
                and not any(p.robot_id == peer.robot_id for p in self._pings.values())
            ):
                ride = self._new_ping(peer, now, src)
                reply = Response(self._origin(), msg.st, "", 0, msg.seq, ride)
                if not self._send(reply, src, to=peer.robot_id):
                    del self._pings[ride]
            else:
                self._answer_ping(msg.origin, msg.seq, src, now)
        if peer is None:
            return
        told = self._advertised()[0]
        if msg.want == WANT_ALL or (msg.want is not None and msg.want_version != told):
            if msg.multicast:
                if len(self._reply_to) < MAX_REPLY_TO:
                    self._reply_to[src] = peer.robot_id
                delay = self.rng.uniform(0, min(float(msg.mx), cfg.reply_delay_max))
                self._reply_at = min(self._reply_at, now + delay)
            else:
                self._serve(peer, src, None, now, have=msg.have)
        elif isinstance(msg.want, tuple):
            self._serve(peer, src, msg.want, now)
        if peer.robot_id in self.peers:
            # A searcher that just started announces its set right after searching.
            self._want_current(peer, now, soon=True)

    def _serve(
        self,
        peer: Peer,
        dst: Addr,
        only: tuple[int, ...] | None,
        now: float,
        have: int | None = None,
    ) -> None:
        """Send parts of our set to `dst` by unicast, once `dst` has proven a round trip; to
        a robot that holds our set `have`, what changed since when we still know that set."""
        if not self._address_proven(dst, now):
            peer.deferred = (dst, only)
            self._challenge(peer, dst, now)
            return
        if have is not None:
            self._repair_asked = now  # it missed a delta: ours carry the steps before them
        compact = self._compact_for(dst)
        parts = self._update_parts(compact)
        catch_up = self._catch_up(have, compact) if have is not None and only is None else None
        if catch_up is not None and parts:
            # One datagram, no bigger than a part: it costs the budget one part.
            if not self._fetch_budget.take(dst[0], now, 1 / (FETCH_SETS_PER_S * len(parts))):
                self.counters.rejects["fetch-limited"] += 1
                return
            self._emit(catch_up, dst, "update", to=peer.robot_id)
            return
        if only is not None and any(i >= len(parts) for i in only):
            only = None  # numbered in another form of the set: send it whole
        wanted = len(parts) if only is None else len(only)
        # Per address, at most FETCH_SETS_PER_S whole sets a second.
        if not parts or not self._fetch_budget.take(
            dst[0], now, wanted / (FETCH_SETS_PER_S * len(parts))
        ):
            self.counters.rejects["fetch-limited"] += 1
            return
        self._send_update_parts(dst, now, only=only, to=peer.robot_id)

    def _on_byebye(self, peer: Peer) -> None:
        if not peer.known:
            self._forget(peer)
            return
        peer.byebye_boot = peer.boot_id
        if peer.reachable:
            peer.reachable = False
            peer.next_ping = math.inf
        self._drop_fetch(peer)
        self._dirty.add(peer.robot_id)

    def _on_update(self, peer: Peer, msg: Update, now: float) -> None:
        """A part of a set, or a delta.  A set not believed yet (its robot has not confirmed
        it in an answer to us) is held, within bounds, and applied once it is."""
        o = msg.origin
        triple = (o.boot_id, o.version, o.digest)
        believed = peer.proven and triple == (peer.boot_id, peer.version, peer.digest)
        if believed and peer.current:
            return  # a duplicate, or parts of a set we completed already
        if msg.base is not None:
            if believed:
                self._apply_delta(peer, msg)
            elif msg.packed is None or len(msg.packed) <= wire.MAX_DATAGRAM:
                peer.held_delta = msg  # (one a robot: the latest)
            return
        f = peer.fetch
        if f is None or (f.boot_id, f.version, f.digest) != triple:
            if f is not None and not believed and (f.boot_id, f.version) >= triple[:2]:
                return  # an older or competing claim than the set being assembled
            self._drop_fetch(peer)
            wait = self.config.fetch_wait if believed else math.inf
            f = peer.fetch = _Fetch(*triple, retry_at=now + wait)
        if f.parts == 0:
            f.parts = msg.parts
        elif f.parts != msg.parts:
            self.counters.rejects["inconsistent-parts"] += 1
            self._drop_fetch(peer)
            return
        if msg.part in f.got:
            return
        if not believed:
            share = max(UNPROVEN_PARTS_MIN, UNPROVEN_PARTS // max(1, self._unproven))
            size = sum(wire.service_json_size(s) for s in msg.services)
            if len(f.got) >= share or self._held_bytes + size > UNPROVEN_BYTES:
                self.counters.rejects["unproven-parts"] += 1
                return
            f.size += size
            self._held_bytes += size
        f.got[msg.part] = msg.services
        if f.missing():
            # More parts are normally right behind this one; ask only if they do not come.
            if believed:
                f.retry_at = max(f.retry_at, now + self.config.fetch_wait)
            return
        if believed:
            self._complete(peer)

    def _complete(self, peer: Peer) -> None:
        """The set being assembled is whole and believed: the peer's services now."""
        f = peer.fetch
        assert f is not None
        services = tuple(s for i in range(f.parts) for s in f.got[i])
        self._drop_fetch(peer)
        if service_digest(services) != f.digest:
            self.counters.rejects["bad-digest"] += 1
            return
        peer.services = services
        peer.held = (f.boot_id, f.version, f.digest)
        self._dirty.add(peer.robot_id)

    def _drop_fetch(self, peer: Peer) -> None:
        if peer.fetch is not None:
            self._held_bytes -= peer.fetch.size
            peer.fetch = None

    def _apply_delta(self, peer: Peer, msg: Update) -> None:
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
                self.counters.rejects[read.reason] += 1
                return
            changed = {s.id: s for s in read[0]}
            gone = set(read[1])
            kept = [changed.pop(s.id, s) for s in services if s.id not in gone]
            services = (*kept, *changed.values())
        if service_digest(services) != o.digest:
            self.counters.rejects["bad-digest"] += 1
            return
        peer.services = services
        peer.held = (o.boot_id, o.version, o.digest)
        self._drop_fetch(peer)
        self._dirty.add(peer.robot_id)

    def _on_response(self, peer: Peer, msg: Response, src: Addr, now: float, proof: bool) -> None:
        if msg.seq is None:
            return
        if msg.ping is not None:  # the peer's ping, riding on its reply to ours
            self._answer_ping(msg.origin, msg.ping, src, now)
        if not proof:
            return
        if peer.deferred is not None:
            dst, only = peer.deferred
            peer.deferred = None
            if dst == src:
                self._serve(peer, dst, only, now)
        if peer.fetch is not None and peer.fetch.retry_at == math.inf:
            peer.fetch.retry_at = now  # held back while it was unproven

    def _round_trip(self, peer: Peer, sample: float, src: Addr, now: float) -> None:
        peer.rtt = sample if peer.rtt is None else 0.8 * peer.rtt + 0.2 * sample
        told = peer.rtt_told
        if told is None or abs(peer.rtt - told) > max(RTT_TELL_S, RTT_TELL_SHARE * told):
            self._dirty.add(peer.robot_id)  # the stored and listed RTT is no longer true
        self._answered[src] = now
        self._settle_ping(peer, ok=True)
