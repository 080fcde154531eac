"""The protocol core's public entry points (`Core`): life cycle, inputs, what arrives and to
which part it goes, outputs."""

from __future__ import annotations

import ipaddress
import math
from collections.abc import Iterable, Sequence

from sdfr import wire
from sdfr.protocol import auth, beacons, challenges, plain, sending, timers, trust, updates
from sdfr.protocol.auth import Keyring
from sdfr.protocol.config import MAX_REPLY_TO, Addr, Outgoing, answers_beacon
from sdfr.protocol.peers import Peer
from sdfr.protocol.state import CoreState
from sdfr.records.model import PeerRecord, Service, service_digest
from sdfr.wire import WANT_ALL, Alive, Byebye, Discovery, Reject, Response, Update

_KIND = {Discovery: "discovery", Response: "response", Update: "update", Alive: "alive"}
#: A Byebye goes out this many times, back to back: nothing repairs a lost one, and a peer
#: that misses it waits three beacons, which at 10 % loss a single copy left one peer in ten
#: to do (a copy of one heard already is dropped on arrival).
BYEBYE_COPIES = 2


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
        beacons.search(self, now)
        updates.send_update_parts(self, None, now)
        # A second search covers a lost first one; beacons cover the rest.
        self._discovery_repeat = now + self.config.reply_delay_max + self.rng.uniform(0.2, 0.5)
        self._next_beacon = now + beacons.beacon_period(self)
        self._next_prune = now + self.config.proven_for

    def stop(self, now: float) -> None:
        """Say goodbye; nothing is sent after this."""
        if self._started and not self._stopped:
            for _ in range(BYEBYE_COPIES):
                sending.send(self, Byebye(self._origin()), None)
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
            sending.send(self, Alive(self._origin(), self.location, self.config.max_age), None)
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
            # At once while announcements are saved up (`update_burst`), else when the next
            # is (one each `update_gap`); what changes meanwhile goes with it.
            wait = max(self.config.update_coalesce, self._update_budget.wait(now))
            self._update_at = min(self._update_at, now + wait)

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
            if seal.reason == "unsigned" and plain.plain_search_allowed(self, data):
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
            plain.on_plain_search(self, msg, src, now)
            return
        origin = msg.origin
        assert origin is not None
        if origin.robot_id == self.config.robot_id:
            challenges.on_own_id(self, msg, origin, src, seal, now)
            return
        if isinstance(msg, Byebye):
            known = self.peers.get(origin.robot_id)
            if known is None or not known.proven:
                if known is not None and not known.known:
                    trust.forget(self, known)
                return  # a robot we never proved leaves: nothing to believe, nothing to ask
            if known.byebye_boot == origin.boot_id:
                return  # a copy of a Byebye heard already (BYEBYE_COPIES): nothing new
        alive = trust.take_proof(self, msg, origin, src, now)
        proof = alive is not None
        ping = isinstance(msg, Discovery) and msg.seq is not None
        peer, believed = trust.gate(self, origin, src, now, seal, alive, ping=ping)
        if isinstance(msg, Discovery):
            self._on_discovery(msg, peer if believed else None, src, now, answer_ping=True)
            if peer is not None and not believed and isinstance(msg.want, str):
                self._remember_search(msg, peer, src, now)
            return
        if peer is None:
            return
        if isinstance(msg, Update):
            # Held until its set is believed (an answer confirms it), applied at once if it is.
            updates.on_update(self, peer, msg, now)
        if not believed:
            if isinstance(msg, Response) and msg.ping is not None and msg.seq is not None:
                challenges.answer_ping(self, origin, msg.ping, src, now)  # let it prove us in turn
            return
        if isinstance(msg, Byebye):
            self._on_byebye(peer)
            return
        trust.heard(self, peer, origin, src, now, getattr(msg, "location", None), proof)
        if isinstance(msg, Response):
            self._on_response(peer, msg, src, now, proof)
        elif (
            isinstance(msg, Alive)
            and msg.seq is not None
            and answers_beacon(self.config.robot_id, msg.seq, msg.turns)
        ):
            # A beacon that is a ping to all who hear it (or to those whose turn it is):
            # answer it (the compact ping reply).
            challenges.answer_ping(self, origin, msg.seq, src, now)
        if peer.robot_id in self.peers and peer.proven:
            # More parts of a whole set are normally right behind this one; a delta we
            # could not apply will not be followed by anything that helps.
            soon = isinstance(msg, Update) and msg.base is None
            updates.want_current(self, peer, now, soon=soon)

    def handle_timer(self, now: float) -> None:
        """Do whatever is due at `now`."""
        timers.handle_timer(self, now)

    def next_deadline(self) -> float | None:
        """When `timers.handle_timer` must run next (None: only an input can change anything)."""
        return timers.next_deadline(self)

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

    # -- message handlers ------------------------------------------------------------------

    def _remember_search(self, msg: Discovery, peer: Peer, src: Addr, now: float) -> None:
        """A search from a robot not believed yet: served (by unicast) once it answers."""
        if not msg.multicast:
            peer.deferred = (src, None if msg.want == WANT_ALL else msg.want)
        elif len(self._reply_to) < MAX_REPLY_TO:
            self._reply_to[src] = peer.robot_id
            delay = self.rng.uniform(0, min(float(msg.mx), self.config.reply_delay_max))
            self._reply_at = min(self._reply_at, now + delay)

    def _targets(self) -> set[str]:
        cfg = self.config
        return {"ssdp:all", wire.DEVICE_TYPE, wire.fleet_target(cfg.fleet), self._me()}

    def _on_discovery(
        self, msg: Discovery, peer: Peer | None, src: Addr, now: float, *, answer_ping: bool
    ) -> None:
        cfg = self.config
        if peer is not None:
            trust.heard(self, peer, msg.origin, src, now, None, False)
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
                ride = beacons.new_ping(self, peer, now, src)
                reply = Response(self._origin(), msg.st, "", 0, msg.seq, ride)
                if not sending.send(self, reply, src, to=peer.robot_id):
                    del self._pings[ride]
            else:
                challenges.answer_ping(self, msg.origin, msg.seq, src, now)
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
                updates.serve(self, peer, src, None, now, have=msg.have)
        elif isinstance(msg.want, tuple):
            updates.serve(self, peer, src, msg.want, now)
        if peer.robot_id in self.peers:
            # A searcher that just started announces its set right after searching.
            updates.want_current(self, peer, now, soon=True)

    def _on_byebye(self, peer: Peer) -> None:
        if not peer.known:
            trust.forget(self, peer)
            return
        peer.byebye_boot = peer.boot_id
        if peer.reachable:
            peer.reachable = False
            peer.next_ping = math.inf
        self._drop_fetch(peer)
        self._dirty.add(peer.robot_id)

    def _on_response(self, peer: Peer, msg: Response, src: Addr, now: float, proof: bool) -> None:
        if msg.seq is None:
            return
        if msg.ping is not None:  # the peer's ping, riding on its reply to ours
            challenges.answer_ping(self, msg.origin, msg.ping, src, now)
        if not proof:
            return
        if peer.deferred is not None:
            dst, only = peer.deferred
            peer.deferred = None
            if dst == src:
                updates.serve(self, peer, dst, only, now)
        if peer.fetch is not None and peer.fetch.retry_at == math.inf:
            peer.fetch.retry_at = now  # held back while it was unproven
