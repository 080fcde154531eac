"""`--addressing auto` in the discovery layer: the address machine (sdfr.protocol.addressing)
carried out on the fleet interface (ARP frames heard and sent, the address given to or taken
from the kernel over netlink, the machine's one timer). Imported only with `--addressing auto`:
a robot with a fixed address never pays for the ARP machinery."""

from __future__ import annotations

import asyncio
import logging
import random
import time
from collections.abc import Callable
from ipaddress import IPv4Address

from sdfr.daemon.arp import ArpSocket, Netlink
from sdfr.daemon.sockets import rearm
from sdfr.host import netif
from sdfr.protocol.addressing import AddrConfig, Addressing, Assign, Release
from sdfr.records import status

log = logging.getLogger("sdfrd.discovery")


class AutoAddress:
    """The address machine of `iface` and its sockets; `on_bound` runs at each pump that
    finds an address bound."""

    def __init__(
        self, fleet: int, iface: str, loop: asyncio.AbstractEventLoop, on_bound: Callable[[], None]
    ) -> None:
        mac = netif.mac(iface)
        self.iface = iface
        self.loop = loop
        self.machine = Addressing(AddrConfig(fleet, mac), random.Random())
        self.arp = ArpSocket(iface, bytes.fromhex(mac.replace(":", "")))
        self.netlink = Netlink(iface)
        #: Set once an address is ours: discovery speaks only from an address that is ours.
        self.bound = asyncio.Event()
        self._on_bound = on_bound
        self._timer: asyncio.TimerHandle | None = None

    def start(self) -> None:
        """Probe for an address, or re-announce ours still on the interface from an earlier
        run."""
        self.loop.add_reader(self.arp.fileno(), self._on_arp)
        current = self._current()
        self.machine.start(time.monotonic(), current)
        self.pump()
        log.info(
            "addressing: %s %s on %s",
            "re-announcing" if current else "probing",
            self.machine.ip,
            self.iface,
        )

    def _current(self) -> IPv4Address | None:
        """Our address still on the interface from an earlier run, if it is one of ours."""
        ip = netif.ipv4(self.iface)
        if ip is None:
            return None
        addr = IPv4Address(ip)
        return addr if addr in self.machine.network else None

    def _on_arp(self) -> None:
        now = time.monotonic()
        for pkt in self.arp.read():
            self.machine.handle_arp(pkt, now)
        self.pump()

    def _on_timer(self) -> None:
        self._timer = None
        self.machine.handle_timer(time.monotonic())
        self.pump()

    def pump(self) -> None:
        """Carry out the address machine's decisions: kernel changes, ARP frames, its timer."""
        machine = self.machine
        for action in machine.actions():
            if isinstance(action, Assign):
                self.netlink.assign(action.ip)
                log.info("addressing: %s is ours", action.ip)
            elif isinstance(action, Release):
                self.netlink.release(action.ip)
                conflict = machine.conflicts[-1] if machine.conflicts else None
                log.warning(
                    "addressing: gave up %s to %s (lower MAC keeps it); probing %s",
                    action.ip,
                    conflict.other_mac if conflict else "another robot",
                    machine.ip,
                )
        for pkt in machine.arp_to_send():
            try:
                self.arp.send(pkt)
            except OSError as exc:
                log.debug("arp send: %s", exc)
        if machine.bound is not None:
            self.bound.set()
            self._on_bound()
        self._timer = rearm(self.loop, self._timer, machine.next_deadline(), self._on_timer)

    def close(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
        self.loop.remove_reader(self.arp.fileno())
        self.arp.close()
        self.netlink.close()

    def signature(self) -> tuple[object, ...]:
        """What changes the status's addressing part."""
        m = self.machine
        return (m.state, m.bound, m.conflicts_total)

    def status(self) -> status.Addressing:
        m = self.machine
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
