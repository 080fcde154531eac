"""The discovery layer's process: owns the UDP socket and the clock, runs the protocol core.

This is the only place of the discovery layer that reads time or touches a
socket; everything it decides comes from `sdfr.protocol.Core`. It persists
the history map to the shared store and reads local registrations from it.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import random
import socket
import struct
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import replace
from ipaddress import IPv4Address
from pathlib import Path
from typing import TYPE_CHECKING

from sdfr import auth, events, keystore, netif, status
from sdfr.config import IFACE_HOST, Config, describe_address, from_args, location_url
from sdfr.daemon import logs, notify
from sdfr.daemon.describe import DescribeServer
from sdfr.daemon.fleetlog import FleetLog
from sdfr.daemon.unknownkeys import UnknownKeys
from sdfr.errors import SdfrError
from sdfr.model import PeerRecord
from sdfr.protocol import Core
from sdfr.store import STATUS_SOCKET, StateWriteError, Store
from sdfr.wire import MESSAGE_TYPES

if TYPE_CHECKING:
    from sdfr.addressing import Addressing
    from sdfr.daemon.arp import ArpSocket, Netlink

log = logging.getLogger("sdfrd.discovery")

#: The layer's tick: its beat to the supervisor, its status to the API layer when it changed,
#: the fallbacks for lost wake-ups (services, keyring), the address check.
#: Every wake-up of an idle daemon costs CPU: 5 s is three beats within STALL_AFTER.
STATUS_PERIOD = 5.0
#: The status file (read by an API layer that has no fresh datagram) is written when what it
#: says changed, and at least this often (seconds): it also proves the state dir writable.
STATUS_FILE_EVERY = 30.0
#: Ticks between the fallbacks for lost wake-ups (the API layer's datagram on discovery.sock
#: says when services or keys change; these look anyway).
SLOW_TICKS = 5
CONTROL_NAME = "discovery.sock"
#: Failures of the layer's callbacks within this many seconds make /health say "failing".
ERROR_WINDOW = 60.0


def open_multicast_socket(cfg: Config, iface: str, source: str = "") -> socket.socket:
    """A UDP socket on the SDfR port, in the group on `iface` only; its multicast datagrams
    from `source` when given (else the kernel's choice)."""
    ifindex = netif.index(iface)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_BINDTODEVICE, iface.encode())
        sock.bind(("0.0.0.0", cfg.port))
        mreqn = struct.pack("4s4si", socket.inet_aton(cfg.group), b"\0" * 4, ifindex)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreqn)
        if source:
            mreqn = struct.pack("4s4si", b"\0" * 4, socket.inet_aton(source), ifindex)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, mreqn)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, cfg.ttl)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 0)
        sock.setblocking(False)
    except OSError as exc:
        sock.close()
        raise SdfrError(
            f"iface: cannot join {cfg.group}:{cfg.port} on {iface}: {exc.strerror or exc}"
        ) from None
    return sock


class DiscoveryLayer:
    """Runs one Core against real sockets until stopped."""

    def __init__(self, cfg: Config, store: Store) -> None:
        if cfg.iface is None or cfg.robot_id is None:
            raise SdfrError("the discovery layer needs --iface and --robot-id")
        self.cfg = cfg
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
        self._errors: deque[float] = deque()
        self._last_error: tuple[float, str] | None = None
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
        self.control = self._open_control(cfg.state_dir / CONTROL_NAME)
        self.addressing: Addressing | None = None
        self.arp: ArpSocket | None = None
        self.netlink: Netlink | None = None
        if cfg.addressing == "auto":
            # (imported here: a robot with a fixed address never pays for the ARP machinery)
            from sdfr.addressing import AddrConfig, Addressing
            from sdfr.daemon.arp import ArpSocket, Netlink

            mac = netif.mac(self.iface)
            self.addressing = Addressing(AddrConfig(cfg.fleet, mac), random.Random())
            self.arp = ArpSocket(self.iface, bytes.fromhex(mac.replace(":", "")))
            self.netlink = Netlink(self.iface)
        self.describe = DescribeServer(self._description)
        self._describe_task: asyncio.Task[None] | None = None
        # The status goes to the API layer over a datagram socket when it changes and when the
        # API asks (before it shows it): no disk, so a full state dir does not look like a
        # dead discovery layer, and no datagram at all while nothing changes.
        self._status_sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._status_sock.setblocking(False)
        self._state_problem: tuple[float, str, str] | None = None
        #: What the status file says (without the heartbeat and counters), and when written.
        self._status_written: tuple[object, float] | None = None
        #: `_status_signature()` when the last whole status was sent.
        self._status_sent: tuple[object, ...] | None = None
        self._description_cache: tuple[tuple[object, ...], bytes] | None = None
        self._addr_timer: asyncio.TimerHandle | None = None
        self._arrivals = 0
        self._bound = asyncio.Event()
        self._timer: asyncio.TimerHandle | None = None
        self._flush_pending = False
        self._stopping = asyncio.Event()

    # -- setup -----------------------------------------------------------------------------

    def _location(self) -> str:
        return location_url(self.cfg.describe, self.address)

    @staticmethod
    def _open_control(path: Path) -> socket.socket:
        """The API layer wakes us through this socket when local services change."""
        path.unlink(missing_ok=True)
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        sock.bind(str(path))
        os.chmod(path, 0o660)
        sock.setblocking(False)
        return sock

    # -- running ---------------------------------------------------------------------------

    async def run(self) -> None:
        notify.on_stop(self.loop, self._stopping.set)
        self._write_status()
        status_task = asyncio.create_task(self._periodic())
        try:
            await self._run()
        finally:
            status_task.cancel()

    async def _run(self) -> None:
        if self.addressing is not None and self.arp is not None:
            self.loop.add_reader(self.arp.fileno(), self._on_arp)
            current = self._current_auto_address()
            self.addressing.start(time.monotonic(), current)
            self._pump_addr()
            log.info(
                "addressing: %s %s on %s",
                "re-announcing" if current else "probing",
                self.addressing.ip,
                self.iface,
            )
            # Discovery speaks only from an address that is ours.
            waiter = asyncio.create_task(self._bound.wait())
            stopper = asyncio.create_task(self._stopping.wait())
            await asyncio.wait({waiter, stopper}, return_when=asyncio.FIRST_COMPLETED)
            waiter.cancel()
            stopper.cancel()
            if self._stopping.is_set():
                self._close_addressing()
                return
        self._check_address()
        await self._serve_description(first=True)  # a failure here leaves no reader behind
        self.loop.add_reader(self.sock.fileno(), self._on_readable)
        self.loop.add_reader(self.control.fileno(), self._on_control)
        self.core.start(time.monotonic())
        self._pump()
        self._starting = False
        self._write_status()
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
            self.control.close()
            (self.cfg.state_dir / CONTROL_NAME).unlink(missing_ok=True)
            self._close_addressing()
            log.info("discovery stopped (byebye sent)")

    # -- addressing (auto mode) ------------------------------------------------------------

    def _current_auto_address(self) -> IPv4Address | None:
        """Our address still on the interface from an earlier run, if it is one of ours."""
        assert self.addressing is not None
        ip = netif.ipv4(self.iface)
        if ip is None:
            return None
        addr = IPv4Address(ip)
        return addr if addr in self.addressing.network else None

    def _on_arp(self) -> None:
        assert self.addressing is not None and self.arp is not None
        now = time.monotonic()
        for pkt in self.arp.read():
            self.addressing.handle_arp(pkt, now)
        self._pump_addr()

    def _on_addr_timer(self) -> None:
        self._addr_timer = None
        assert self.addressing is not None
        self.addressing.handle_timer(time.monotonic())
        self._pump_addr()

    def _pump_addr(self) -> None:
        """Carry out the address machine's decisions: kernel changes, ARP frames, its timer."""
        machine, arp, netlink = self.addressing, self.arp, self.netlink
        if machine is None or arp is None or netlink is None:
            return
        from sdfr.addressing import Assign, Release

        for action in machine.actions():
            if isinstance(action, Assign):
                netlink.assign(action.ip)
                log.info("addressing: %s is ours", action.ip)
            elif isinstance(action, Release):
                netlink.release(action.ip)
                conflict = machine.conflicts[-1] if machine.conflicts else None
                log.warning(
                    "addressing: gave up %s to %s (lower MAC keeps it); probing %s",
                    action.ip,
                    conflict.other_mac if conflict else "another robot",
                    machine.ip,
                )
        for pkt in machine.arp_to_send():
            try:
                arp.send(pkt)
            except OSError as exc:
                log.debug("arp send: %s", exc)
        if machine.bound is not None:
            self._bound.set()
            if self.core.started:
                self._check_address()
        deadline = machine.next_deadline()
        if self._addr_timer is not None and (
            deadline is None or self._addr_timer.when() != deadline
        ):
            self._addr_timer.cancel()
            self._addr_timer = None
        if deadline is not None and self._addr_timer is None:
            self._addr_timer = self.loop.call_at(deadline, self._on_addr_timer)

    def _close_addressing(self) -> None:
        if self._addr_timer is not None:
            self._addr_timer.cancel()
        if self.arp is not None:
            self.loop.remove_reader(self.arp.fileno())
            self.arp.close()
        if self.netlink is not None:
            self.netlink.close()

    async def _periodic(self) -> None:
        tick = 0
        while True:
            notify.beat()
            await asyncio.sleep(STATUS_PERIOD)
            tick += 1
            self._guard("periodic duties", self._check_address)
            self._guard("logging the fleet", lambda: self.fleet_log.tick(time.monotonic()))
            if tick % SLOW_TICKS == 0:
                self._guard("reloading the services", self._reload_services)
                self._guard("reloading the keyring", self._reload_keyring)
            written = self._status_written
            if (
                self._status_signature() != self._status_sent
                or written is None
                or time.monotonic() - written[1] >= STATUS_FILE_EVERY
            ):
                self._guard("writing the status", self._write_status)
            if self.core.has_dirty:
                self._guard("saving the history map", self._save)

    def _status_signature(self) -> tuple[object, ...]:
        """What changes the status record besides its heartbeat and counters, cheaply."""
        core, machine, conflict = self.core, self.addressing, self.core.conflict
        return (
            self._starting,
            core.version,
            sum(1 for p in core.peers.values() if p.reachable),
            len(core.peers),
            self.address,
            core.location,
            len(self._errors),
            self._last_error,
            self._state_problem,
            core.announce_error,
            None if machine is None else (machine.state, machine.bound, machine.conflicts_total),
            None if conflict is None else conflict.count,
            self.describe.where,
            self._keyring_stamp,
            self.unknown_keys.kids(time.monotonic()),
        )

    def _guard(self, what: str, duty: Callable[[], None]) -> None:
        """Run a callback's work; a failure is logged and counted (for /health), and the
        layer goes on: one bad datagram or a full disk must not stop discovery."""
        try:
            duty()
        except Exception as exc:
            now = time.time()
            self._errors.append(now)
            self._recent_errors(now)
            message = f"{what} failed: {type(exc).__name__}: {exc}"
            if self._last_error is None or self._last_error[1] != message:
                log.exception("%s", message)  # each new failure once, with its traceback
            self._last_error = (now, message)

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
            if addr[0] == self.address and self.addressing is not None:
                # Another robot sends from our address: a conflict, typically after a merge.
                self.addressing.suspect(now)
            unknown = self.core.counters.rejects["unknown-key"]
            self.core.receive(data, (addr[0], addr[1]), now)
            if self.core.counters.rejects["unknown-key"] != unknown:
                self._unknown_key(data, addr[0], now)
        if self.addressing is not None and self.core.arrivals != self._arrivals:
            self._arrivals = self.core.arrivals
            self.addressing.refresh(now)
        self._log_conflict()  # (at once, not at the next tick)
        self._pump_addr()

    def _on_control(self) -> None:
        asked = False
        while True:
            try:
                asked |= self.control.recv(64).startswith(b"status")
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                break
        if asked:  # an API layer that just started: our status at once, not within a tick
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
        if self.core.has_dirty and not self._flush_pending and self._state_problem is None:
            self._flush_pending = True
            self.loop.call_soon(self._flush)
        deadline = self.core.next_deadline()
        if self._timer is not None and (deadline is None or self._timer.when() != deadline):
            self._timer.cancel()
            self._timer = None
        if deadline is not None and self._timer is None:
            # loop.time() is time.monotonic() on Linux's default loop.
            self._timer = self.loop.call_at(deadline, self._on_timer)

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
            self._state_failed(exc)
        else:
            if self._state_problem is not None and (views or removed):
                # It can be written again: say so now, not at the next status file rewrite.
                self._state_problem = None
                self._status_written = None

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
            self._wake_api(b"events\n")

    def _wake_api(self, message: bytes) -> None:
        with contextlib.suppress(OSError):  # no API layer listening: it polls too
            self._status_sock.sendto(message, str(self.cfg.state_dir / STATUS_SOCKET))

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

    def _send_status(self, record: dict[str, object] | None = None) -> None:
        """Our status (`record`, else made now) to the API layer: a datagram, no disk."""
        if record is None:
            record = self._status().to_json()
        self._status_sent = self._status_signature()
        with contextlib.suppress(OSError):  # no API layer listening: it reads the file later
            self._status_sock.sendto(
                json.dumps(record, separators=(",", ":")).encode(),
                str(self.cfg.state_dir / STATUS_SOCKET),
            )

    def _write_status(self) -> None:
        """The status to the API layer, and to the file when what it says changed (the
        heartbeat and the counters aside) or STATUS_FILE_EVERY has passed: replacing a file
        every tick was the layer's largest idle cost."""
        record = self._status().to_json()
        self._send_status(record)
        key = {k: v for k, v in record.items() if k not in ("heartbeat", "counters")}
        now = time.monotonic()
        last = self._status_written
        if last is not None and last[0] == key and now - last[1] < STATUS_FILE_EVERY:
            return
        try:
            self.store.write_status(record)
        except StateWriteError as exc:
            self._state_failed(exc)
            self._status_written = None
        else:
            self._state_problem = None
            self._status_written = (key, now)

    def _state_failed(self, exc: StateWriteError) -> None:
        """A write of the state dir failed (full, read-only): say so in the status, log it
        once a minute (the log filter), and go on discovering."""
        if self._state_problem is None or self._state_problem[1] != exc.reason:
            log.error("%s", exc)
        self._state_problem = (time.time(), exc.reason, str(exc))

    def _status(self) -> status.DiscoveryStatus:
        c = self.core.counters
        problem = self._state_problem
        return status.DiscoveryStatus(
            pid=os.getpid(),
            heartbeat=time.time(),
            thread=None
            if threading.current_thread() is threading.main_thread()
            else threading.get_native_id(),
            starting=self._starting,
            robot_id=self.cfg.robot_id,
            fleet=self.cfg.fleet,
            iface=self.iface,
            address=self.address,
            boot_id=self.boot_id,
            version=self.core.version,
            started=self.started,
            location=self.core.location,
            peers_reachable=sum(1 for p in self.core.peers.values() if p.reachable),
            peers_known=len(self.core.peers),
            addressing=self._addressing_status(),
            counters=status.Counters(
                datagrams_in={k: c.datagrams_in[k] for k in MESSAGE_TYPES},
                datagrams_out={k: c.datagrams_out[k] for k in MESSAGE_TYPES},
                bytes_in=c.bytes_in,
                bytes_out=c.bytes_out,
                rejects=dict(c.rejects),
                challenges=c.challenges,
                challenges_limited=c.challenges_limited,
                invites=c.invites,
            ),
            auth=self._auth_status(),
            describe=self.describe.status(),
            robot_id_conflict=self._conflict_status(),
            errors=self._error_status(),
            state=status.StateDir()
            if problem is None
            else status.StateDir(writable=False, reason=problem[1], error=problem[2]),
        )

    def _auth_status(self) -> status.Auth:
        ring = self.core.keyring
        offset = self.clock_offset
        return status.Auth(
            mode=ring.mode if ring.keyed else "open",
            primary=ring.primary,
            keys=tuple(sorted(ring.keys)),
            received=dict(self.core.counters.verified),
            ssdp_interop=self.core.ssdp_interop,
            unknown=tuple(
                status.UnknownKey(
                    s.kid, s.address, s.count, s.first_seen + offset, s.last_seen + offset
                )
                for s in self.unknown_keys.recent(time.monotonic())
            ),
        )

    def _conflict_status(self) -> status.Conflict | None:
        c = self.core.conflict
        if c is None:
            return None
        return status.Conflict(c.address, c.boot_id, c.last_seen + self.clock_offset, c.count)

    def _recent_errors(self, now: float) -> int:
        """Callback failures within the last ERROR_WINDOW (older ones are forgotten)."""
        while self._errors and self._errors[0] < now - ERROR_WINDOW:
            self._errors.popleft()
        return len(self._errors)

    def _error_status(self) -> status.Errors:
        last = self._last_error
        return status.Errors(
            recent=self._recent_errors(time.time()),
            last=None if last is None else last[1],
            last_at=None if last is None else last[0],
            # Not a crash, but as bad: the fleet cannot see our services.
            persistent=self.core.announce_error,
        )

    def _addressing_status(self) -> status.Addressing:
        m = self.addressing
        if m is None:
            return status.Addressing()
        return status.Addressing(
            mode="auto",
            state=m.state.value,
            address=str(m.bound) if m.bound else None,
            conflicts=tuple(
                status.AddressConflict(str(c.ip), c.other_mac, c.kept, c.phase)
                for c in list(m.conflicts)[-10:]
            ),
            conflicts_total=m.conflicts_total,
        )


async def _amain(cfg: Config) -> None:
    store = Store(cfg.state_dir)
    try:
        layer = DiscoveryLayer(cfg, store)
        await layer.run()
    finally:
        store.close()


def main(argv: list[str] | None = None) -> int:
    try:
        cfg = from_args(argv)
    except SdfrError as exc:
        print(f"sdfrd[discovery]: {exc}", flush=True)
        return 2
    logs.setup("discovery", cfg.log_level, cfg.log_format)
    try:
        asyncio.run(_amain(cfg))
    except SdfrError as exc:
        log.error("%s", exc)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
