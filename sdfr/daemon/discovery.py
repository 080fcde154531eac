"""The discovery layer: owns the UDP socket and the clock, runs the protocol core.

Everything it decides comes from `sdfr.protocol.Core`; this module carries it out: datagrams
in and out, the core's timer, the description server's address. It persists the history map
to the shared store, reads the local registrations and the keyring when the API layer says
they changed (sdfr.daemon.channel) or at its slow ticks, and sends its status. Its parts:
`sockets` (the multicast socket, a machine's one timer), `reporting` (the status record and
where it goes), `autoaddr` (`--addressing auto` only).
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import random
import socket
import time
from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING

from sdfr.config import keystore
from sdfr.config.load import IFACE_HOST, Config, describe_address, from_args, location_url
from sdfr.daemon import channel, logs, reporting
from sdfr.daemon.channel import Host
from sdfr.daemon.describe import DescribeServer
from sdfr.daemon.fleetlog import FleetLog
from sdfr.daemon.sockets import open_multicast_socket, rearm
from sdfr.daemon.unknownkeys import UnknownKeys
from sdfr.errors import SdfrError
from sdfr.host import netif
from sdfr.protocol import Core, auth
from sdfr.records import events, status
from sdfr.records.model import PeerRecord
from sdfr.store import StateWriteError, Store

if TYPE_CHECKING:
    from sdfr.daemon.autoaddr import AutoAddress
    from sdfr.host.wifiwatch import Watch

log = logging.getLogger("sdfrd.discovery")

#: The layer's tick: its beat to the supervisor, its status to the API layer when it changed,
#: the fallbacks for lost wake-ups (services, keyring), the address check.
#: Every wake-up of an idle daemon costs CPU: 5 s is three beats within STALL_AFTER.
STATUS_PERIOD = 5.0
#: Ticks between the fallbacks for lost wake-ups (the API layer's SERVICES datagram says when
#: services or keys change; these look anyway).
SLOW_TICKS = 5


class DiscoveryLayer:
    """Runs one Core against real sockets until stopped."""

    def __init__(self, cfg: Config, store: Store, host: Host | None = None) -> None:
        if cfg.iface is None or cfg.robot_id is None:
            raise SdfrError("the discovery layer needs --iface and --robot-id")
        self.cfg = cfg
        self.host = host or Host()
        self.iface: str = cfg.iface
        self.store = store
        self.loop = asyncio.get_running_loop()
        self.clock_offset = time.time() - time.monotonic()
        self.started = time.time()
        #: Until `_run` has started the core: /health says "starting", not "up".
        self._starting = True
        self.boot_id = store.next_boot_id(time.time())
        version, services = store.local_state()
        self.keyring_path = keystore.keyring_path(cfg.state_dir)
        self._keyring_stamp = self._stamp()
        keyring = keystore.load_keyring(cfg.state_dir)
        self.failures = reporting.Failures()
        self._conflict_logged = 0  # the conflict's datagram count when last logged
        #: Datagrams sealed with keys the keyring does not hold, for as long as a peer heard
        #: would stay listed (a robot left out of a key rotation is said, not just counted).
        self.unknown_keys = UnknownKeys(cfg.miss_limit * cfg.beacon_interval)
        self.address = netif.ipv4(self.iface) or ""
        self.core = Core(
            cfg.core_config(),
            boot_id=self.boot_id,
            rng=random.SystemRandom(),  # the pings' nonces must be unguessable
            location=self._location(),
            version=version,
            services=services,
            keyring=keyring,
        )
        self.core.set_subnet(netif.ipv4_network(self.iface) if self.address else None)
        saved = store.load_peers()
        history = [r.shifted(-self.clock_offset) for r in saved]
        self.core.restore(history)
        #: The fleet's changes in the log, one line each (on the core's clock).
        self.fleet_log = FleetLog(replace(r, reachable=False) for r in history)
        # Nobody is reachable before we hear them again: tell the changes feed so.
        store.mark_all_unreachable(events.unreachable_at_start(saved))
        self.tracker = events.Tracker(
            cfg.indicator_thresholds, [replace(r, reachable=False) for r in saved]
        )
        # On lo the kernel sends multicast from 0.0.0.0 or another interface's address
        # (127.0.0.1 is host-scoped): from the address our LOCATION names, the core knows the
        # echo it hears there for its own, not another sender's claim of our robot id.
        loopback = netif.is_loopback(self.iface)
        self.sock = open_multicast_socket(cfg, self.iface, self.address if loopback else "")
        self.control = channel.open_control(cfg.state_dir)
        #: `--addressing auto`'s machine and sockets (imported only then).
        self.auto: AutoAddress | None = None
        if cfg.addressing == "auto":
            from sdfr.daemon.autoaddr import AutoAddress

            self.auto = AutoAddress(cfg.fleet, self.iface, self.loop, self._on_bound)
        self.describe = DescribeServer(self._description)
        self._describe_task: asyncio.Task[None] | None = None
        # The status goes to the API layer when it changes and when the API asks (before it
        # shows it), and no datagram at all while nothing changes.
        self.out = reporting.StatusOut(cfg.state_dir, store)
        self._description_cache: tuple[tuple[object, ...], bytes] | None = None
        self._arrivals = 0
        self._timer: asyncio.TimerHandle | None = None
        self._flush_pending = False
        self._stopping = asyncio.Event()
        #: The fleet's WiFi, when sdfrd joined it: who refuses our key (imported only then).
        self.wifi: Watch | None = None
        self.wifi_state: status.Wifi | None = None
        self._wifi_next = 0.0
        #: A look at the stations under way (`iw` in a thread); its task, kept while it runs.
        self._wifi_look: asyncio.Task[None] | None = None
        if cfg.wifi_wanted:  # (wifiwatch is not even loaded otherwise)
            from sdfr.host import wifiwatch

            self.wifi = wifiwatch.watch_for(cfg)

    # -- setup -----------------------------------------------------------------------------

    def _location(self) -> str:
        return location_url(self.cfg.describe, self.address)

    # -- running ---------------------------------------------------------------------------

    async def run(self) -> None:
        self.host.on_stop(self.loop, self._stopping.set)
        self._write_status()
        status_task = asyncio.create_task(self._periodic())
        try:
            await self._run()
        finally:
            status_task.cancel()

    async def _run(self) -> None:
        if self.auto is not None:
            self.auto.start()
            # Discovery speaks only from an address that is ours.
            waiter = asyncio.create_task(self.auto.bound.wait())
            stopper = asyncio.create_task(self._stopping.wait())
            await asyncio.wait({waiter, stopper}, return_when=asyncio.FIRST_COMPLETED)
            waiter.cancel()
            stopper.cancel()
            if self._stopping.is_set():
                self.auto.close()
                return
        self.loop.add_reader(self.sock.fileno(), self._on_readable)
        self.loop.add_reader(self.control.fileno(), self._on_control)
        try:
            self._check_address()
            await self._serve_description(first=True)
        except BaseException:  # a start that fails leaves no reader behind
            self.loop.remove_reader(self.sock.fileno())
            self.loop.remove_reader(self.control.fileno())
            raise
        self.core.start(time.monotonic())
        self._pump()
        self._starting = False
        self._write_status()
        self.host.beat()  # serving, and the API layer told first: systemd may hear READY=1
        log.info(
            "discovery up: robot %s fleet %d on %s (%s), boot %d; %d robots known from before",
            self.cfg.robot_id,
            self.cfg.fleet,
            self.iface,
            self.address or "no address",
            self.boot_id,
            len(self.core.peers),
        )
        try:
            await self._stopping.wait()
        finally:
            self.core.stop(time.monotonic())
            self._pump()
            self._flush()
            self.loop.remove_reader(self.sock.fileno())
            self.loop.remove_reader(self.control.fileno())
            self.describe.close()
            self.sock.close()
            channel.close_control(self.control, self.cfg.state_dir)
            if self.auto is not None:
                self.auto.close()
            log.info("discovery stopped (byebye sent)")

    def _on_bound(self) -> None:
        """`--addressing auto` found our address bound: follow it once discovering."""
        if self.core.started:
            self._check_address()

    async def _periodic(self) -> None:
        tick = 0
        while True:
            self.host.beat(starting=self._starting)
            await asyncio.sleep(STATUS_PERIOD)
            tick += 1
            self._guard("periodic duties", self._check_address)
            self._guard("logging the fleet", lambda: self.fleet_log.tick(time.monotonic()))
            if self.wifi is not None:
                self._guard("watching the WiFi", self._watch_wifi)
            if tick % SLOW_TICKS == 0:
                self._guard("reloading the services", self._reload_services)
                self._guard("reloading the keyring", self._reload_keyring)
            if self.out.due(self._status_signature()):
                self._guard("writing the status", self._write_status)
            if self.core.has_dirty:
                self._guard("saving the history map", self._save)

    def _watch_wifi(self) -> None:
        """Look at the WiFi's stations when a look is due and none is under way: `iw` runs in
        a thread, so a slow radio (or a slow `iw`) never holds back beacons and answers."""
        if self.wifi is None or time.monotonic() < self._wifi_next or self._wifi_look:
            return
        self._wifi_look = self.loop.create_task(self._look_at_wifi(self.wifi))

    async def _look_at_wifi(self, watch: Watch) -> None:
        from sdfr.host import wifiwatch

        try:
            stations = await asyncio.to_thread(wifiwatch.station_dump, watch.iface)
        finally:
            self._wifi_look = None

        def seen() -> None:
            now = time.monotonic()
            self.wifi_state, lines = watch.observe(now, stations)
            early = time.time() - self.started < wifiwatch.FIRST_MINUTE
            soon = early or watch.pending
            self._wifi_next = now + (wifiwatch.FIRST_PERIOD if soon else wifiwatch.PERIOD)
            for line in lines:
                log.warning("%s", line)

        self._guard("watching the WiFi", seen)

    def _status_signature(self) -> tuple[object, ...]:
        """What changes the status record besides its heartbeat and counters, cheaply."""
        core, auto, conflict = self.core, self.auto, self.core.conflict
        return (
            self._starting,
            core.version,
            sum(1 for p in core.peers.values() if p.reachable),
            len(core.peers),
            self.address,
            core.location,
            self.failures.signature(),
            self.out.problem,
            core.announce_error,
            None if auto is None else auto.signature(),
            None if conflict is None else conflict.count,
            self.describe.where,
            self._keyring_stamp,
            self.unknown_keys.kids(time.monotonic()),
            None if self.wifi_state is None else self.wifi_state.authorized,
            None if self.wifi_state is None else [s.mac for s in self.wifi_state.refused],
        )

    def _guard(self, what: str, duty: Callable[[], None]) -> None:
        """Run a callback's work; a failure is logged and counted (for /health), and the
        layer goes on: one bad datagram or a full disk must not stop discovery."""
        try:
            duty()
        except Exception as exc:
            message = f"{what} failed: {type(exc).__name__}: {exc}"
            if self.failures.add(time.time(), message):
                log.exception("%s", message)  # each new failure once, with its traceback

    def _on_readable(self) -> None:
        self._guard("receiving", self._receive)
        self._guard("sending", self._pump)

    def _receive(self) -> None:
        now = time.monotonic()
        for _ in range(256):
            try:
                data, addr = self.sock.recvfrom(2048)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:
                log.debug("recvfrom: %s", exc)
                break
            if addr[0] == self.address and self.auto is not None:
                # Another robot sends from our address: a conflict, typically after a merge.
                self.auto.machine.suspect(now)
            unknown = self.core.counters.rejects["unknown-key"]
            self.core.receive(data, (addr[0], addr[1]), now)
            if self.core.counters.rejects["unknown-key"] != unknown:
                self._unknown_key(data, addr[0], now)
        if self.auto is not None and self.core.arrivals != self._arrivals:
            self._arrivals = self.core.arrivals
            self.auto.machine.refresh(now)
        self._log_conflict()  # (at once, not at the next tick)
        if self.auto is not None:
            self.auto.pump()

    def _on_control(self) -> None:
        if channel.status_asked(self.control):
            # Asked by an API layer (just started, or about to show it): now, not at a tick.
            self._guard("sending the status", self._send_status)
            return
        self._guard("reloading the keyring", self._reload_keyring)
        self._guard("reloading the services", self._reload_services)
        self._guard("sending", self._pump)

    def _on_timer(self) -> None:
        self._timer = None
        self._guard("timer", lambda: self.core.handle_timer(time.monotonic()))
        self._guard("sending", self._pump)

    def _pump(self) -> None:
        """Send what the core wants sent, persist what changed, re-arm the one timer."""
        group = (self.cfg.group, self.cfg.port)
        now = time.monotonic()
        for data, dst in self.core.datagrams_to_send():
            try:
                if dst is not None and self.core.round_trip_proven(dst, now):
                    # Our pings to it come back: tell the kernel, so that it keeps the
                    # neighbour entry reachable instead of probing it with ARP (which a lossy
                    # link can fail, and then unicasts wait on a new resolution).
                    self.sock.sendto(data, socket.MSG_CONFIRM, dst)
                else:
                    self.sock.sendto(data, dst if dst is not None else group)
            except OSError as exc:
                self.core.counters.rejects["send-error"] += 1
                log.debug("sendto %s: %s", dst or group, exc)
        if self.core.has_dirty and not self._flush_pending and self.out.problem is None:
            self._flush_pending = True
            self.loop.call_soon(self._flush)
        self._timer = rearm(self.loop, self._timer, self.core.next_deadline(), self._on_timer)

    def _flush(self) -> None:
        self._flush_pending = False
        self._guard("saving the history map", self._save)

    def _save(self) -> None:
        removed = self.core.take_removed()
        views = self.core.take_dirty()
        now = time.monotonic()
        self._guard("logging the fleet", lambda: self.fleet_log.observe(removed, views, now))
        try:
            self._save_views(removed, views)
        except StateWriteError as exc:
            # Kept to be saved again: the next periodic tick tries (when there is room).
            self.core.mark_unsaved([v.robot_id for v in views], removed)
            self.out.failed(exc)
        else:
            if self.out.problem is not None and (views or removed):
                self.out.recovered()

    def _save_views(self, removed: list[str], views: list[PeerRecord]) -> None:
        """Save what changed in the history map, with the events it makes, in one
        transaction; then wake the API layer's event streams."""
        records = [v.shifted(self.clock_offset) for v in views]
        undo = self.tracker.checkpoint()
        told = [self.tracker.forget(r) for r in removed]
        for record in records:
            told += self.tracker.observe(record)
        try:
            self.store.save_history(removed, records, told)
        except StateWriteError:
            self.tracker.rollback(undo)  # told again with the next try
            raise
        if told:
            self.out.to_api.send(channel.EVENTS)

    def _stamp(self) -> tuple[int, int, int] | None:
        try:
            st = self.keyring_path.stat()
        except FileNotFoundError:
            return None
        return (st.st_ino, st.st_mtime_ns, st.st_size)

    def _reload_keyring(self) -> None:
        """The API layer rewrites keyring.json (sdfr keys ...): take the new keyring."""
        stamp = self._stamp()
        if stamp == self._keyring_stamp:
            return
        keyring = keystore.load_keyring(self.cfg.state_dir)
        self._keyring_stamp = stamp
        if keyring != self.core.keyring:
            self.core.set_keyring(keyring)
            log.info(
                "keyring: %s, sending with %s, accepting %s",
                keyring.mode if keyring.keyed else "open (no key)",
                keyring.primary if keyring.signs else "no key",
                ", ".join(sorted(keyring.keys)) or "unsigned datagrams only",
            )

    def _reload_services(self) -> None:
        version = self.store.local_version()
        if version != self.core.version:
            version, services = self.store.local_state()
            self.core.set_services(version, services, time.monotonic())
            self._pump()

    def _check_address(self) -> None:
        address = netif.ipv4(self.iface, self.sock) or ""
        if address != self.address:
            log.info("address of %s is now %s", self.iface, address or "none")
            self.address = address
            if address:
                self.core.set_subnet(netif.ipv4_network(self.iface, self.sock))
                self.core.set_location(self._location(), time.monotonic())
                self._pump()
            if self.core.started:
                self._describe_task = self.loop.create_task(self._serve_description())

    async def _serve_description(self, *, first: bool = False) -> None:
        """Serve the description where `describe` says: on the fleet interface's address
        (followed when it changes) unless another address is configured."""
        host, port = describe_address(self.cfg.describe)
        if host == IFACE_HOST:
            if not self.address:
                self.describe.close()
                return
            host = self.address
        try:
            await self.describe.listen(host, port)
        except OSError as exc:
            message = f"describe: cannot listen on {host}:{port}: {exc.strerror or exc}"
            if first:
                raise SdfrError(message) from None
            log.error("%s", message)

    def _description(self) -> bytes:
        """The description's JSON, made again only when what it shows changed."""
        core = self.core
        key = (core.version, self.address, self.boot_id)
        if self._description_cache is None or self._description_cache[0] != key:
            body = {
                "robot_id": self.cfg.robot_id,
                "fleet": self.cfg.fleet,
                "address": self.address,
                "boot_id": self.boot_id,
                "version": core.version,
                "services": [s.to_json() for s in core.services],
            }
            data = json.dumps(body, ensure_ascii=False, separators=(",", ":")).encode()
            self._description_cache = (key, data)
        return self._description_cache[1]

    def _log_conflict(self) -> None:
        """Say so while another sender claims our robot id (the log's RepeatFilter writes it
        once a minute at most)."""
        c = self.core.conflict
        if c is not None and c.count != self._conflict_logged:
            self._conflict_logged = c.count
            log.warning(
                "another sender claims robot id %s: %s (boot %d, %d datagrams so far); two "
                "daemons with one id fight over it: give each its own --robot-id",
                self.cfg.robot_id,
                c.address,
                c.boot_id,
                c.count,
            )

    def _unknown_key(self, data: bytes, address: str, now: float) -> None:
        """`data` from `address` was refused: sealed with a key the keyring does not hold.
        Noted, and said in the log once a minute per key id."""
        seal = auth.seal_of(data)
        if seal is None:
            return
        seen = self.unknown_keys.saw(seal.kid, address, now)
        if seen is not None:
            log.warning(
                "datagrams sealed with key %s, which this robot's keyring does not hold, come "
                "from %s (%d in %.0f s), and are dropped: a robot left out of a key rotation? "
                "Give it the fleet's key, or `sdfr keys install` its key here; `sdfr keys "
                "list` shows the keys seen",
                seen.kid,
                address,
                seen.count,
                now - seen.first_seen,
            )

    def _send_status(self) -> None:
        """Our status to the API layer: a datagram, no disk."""
        self.out.send(self._status().to_json(), self._status_signature())

    def _write_status(self) -> None:
        """Our status to the API layer, and to the status file when due (StatusOut.write)."""
        self.out.write(self._status().to_json(), self._status_signature())

    def _status(self) -> status.DiscoveryStatus:
        core = self.core
        return status.DiscoveryStatus(
            pid=os.getpid(),
            heartbeat=time.time(),
            thread=reporting.thread_id(),
            starting=self._starting,
            robot_id=self.cfg.robot_id,
            fleet=self.cfg.fleet,
            iface=self.iface,
            address=self.address,
            boot_id=self.boot_id,
            version=core.version,
            started=self.started,
            location=core.location,
            peers_reachable=sum(1 for p in core.peers.values() if p.reachable),
            peers_known=len(core.peers),
            addressing=status.Addressing() if self.auto is None else self.auto.status(),
            counters=reporting.counters(core),
            auth=reporting.auth(core, self.unknown_keys, self.clock_offset),
            describe=self.describe.status(),
            robot_id_conflict=reporting.conflict(core, self.clock_offset),
            # A persistent error is not a crash, but as bad: the fleet cannot see our services.
            errors=self.failures.status(core.announce_error),
            state=reporting.state_dir(self.out.problem),
            wifi=self.wifi_state,
        )


async def _amain(cfg: Config, host: Host) -> None:
    store = Store(cfg.state_dir)
    try:
        layer = DiscoveryLayer(cfg, store, host)
        await layer.run()
    finally:
        store.close()


def main(argv: list[str] | None = None, host: Host | None = None) -> int:
    """The discovery layer (`host`: what its supervisor gave it; None: it runs alone)."""
    try:
        cfg = from_args(argv)
    except SdfrError as exc:
        print(f"sdfrd[discovery]: {exc}", flush=True)
        return 2
    logs.setup("discovery", cfg.log_level, cfg.log_format)
    try:
        asyncio.run(_amain(cfg, host or Host()))
    except SdfrError as exc:
        log.error("%s", exc)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
