"""The address layer's I/O: ARP on a raw packet socket, addresses through netlink.

Thin on purpose: every decision is `sdfr.protocol.addressing.Addressing`'s; this
module only turns frames into `Arp` records and `ArpSend`/`Assign`/`Release`
into frames and kernel calls.
"""

from __future__ import annotations

import contextlib
import socket
import struct
from concurrent.futures import ThreadPoolExecutor
from ipaddress import IPv4Address
from typing import Any

from sdfr.errors import SdfrError
from sdfr.protocol.addressing import PREFIX_LEN, ZERO, Arp, ArpSend

ETH_P_ARP = 0x0806
BROADCAST = b"\xff" * 6
_ARP = struct.Struct("!HHBBH6s4s6s4s")  # htype ptype hlen plen op sha spa tha tpa


def _mac_text(raw: bytes) -> str:
    return ":".join(f"{b:02x}" for b in raw)


def parse(frame: bytes) -> Arp | None:
    """An Ethernet frame carrying IPv4-over-Ethernet ARP, else None."""
    if len(frame) < 14 + _ARP.size or frame[12:14] != b"\x08\x06":
        return None
    htype, ptype, hlen, plen, op, sha, spa, _tha, tpa = _ARP.unpack_from(frame, 14)
    if htype != 1 or ptype != 0x0800 or hlen != 6 or plen != 4 or op not in (1, 2):
        return None
    return Arp(op, _mac_text(sha), IPv4Address(spa), IPv4Address(tpa))


def build(send: ArpSend, mac: bytes) -> bytes:
    """An ARP request: a probe asks for `ip` from 0.0.0.0; an announcement claims `ip`."""
    sender = ZERO if send.kind == "probe" else send.ip
    arp = _ARP.pack(1, 0x0800, 6, 4, 1, mac, sender.packed, b"\0" * 6, send.ip.packed)
    return BROADCAST + mac + b"\x08\x06" + arp


class ArpSocket:
    """A raw socket seeing every ARP frame on one interface."""

    def __init__(self, iface: str, mac: bytes) -> None:
        self.iface = iface
        self.mac = mac
        try:
            self.sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_ARP))
            self.sock.bind((iface, ETH_P_ARP))
        except OSError as exc:
            raise SdfrError(
                f"addressing: cannot open an ARP socket on {iface}: {exc.strerror or exc} "
                "(auto addressing needs root or CAP_NET_RAW)"
            ) from None
        self.sock.setblocking(False)

    def fileno(self) -> int:
        return self.sock.fileno()

    def read(self) -> list[Arp]:
        out: list[Arp] = []
        for _ in range(256):
            try:
                frame = self.sock.recv(2048)
            except (BlockingIOError, InterruptedError):
                break
            pkt = parse(frame)
            if pkt is not None:
                out.append(pkt)
        return out

    def send(self, pkt: ArpSend) -> None:
        self.sock.send(build(pkt, self.mac))

    def close(self) -> None:
        self.sock.close()


class Netlink:
    """Adds and removes this robot's address on its interface (pyroute2).

    pyroute2's synchronous IPRoute runs an event loop of its own, which it
    cannot do inside the daemon's; so it lives in one worker thread, and each
    call (a millisecond or so) waits for its result there.
    """

    TIMEOUT = 5.0

    def __init__(self, iface: str) -> None:
        self.iface = iface
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="netlink")
        try:
            self.ipr, self.index = self._pool.submit(self._open).result(self.TIMEOUT)
        except BaseException:
            self._pool.shutdown(wait=False)
            raise

    def _open(self) -> tuple[Any, int]:
        from sdfr.daemon import allow_openssl

        allow_openssl()  # (pyroute2 imports ssl)
        from pyroute2 import IPRoute

        ipr = IPRoute()
        links = ipr.link_lookup(ifname=self.iface)
        if not links:
            ipr.close()
            raise SdfrError(f"iface: no interface named {self.iface!r}")
        return ipr, int(links[0])

    def _call(self, what: str, command: str, ip: IPv4Address) -> None:
        def run() -> None:
            self.ipr.addr(command, index=self.index, address=str(ip), prefixlen=PREFIX_LEN)

        try:
            self._pool.submit(run).result(self.TIMEOUT)
        except Exception as exc:  # NetlinkError or a timeout: say what failed, in words
            raise SdfrError(
                f"addressing: cannot {what} {ip}/{PREFIX_LEN} on {self.iface}: {exc}"
            ) from None

    def assign(self, ip: IPv4Address) -> None:
        self._call("add", "replace", ip)

    def release(self, ip: IPv4Address) -> None:
        self._call("remove", "del", ip)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._pool.submit(self.ipr.close).result(self.TIMEOUT)
        self._pool.shutdown(wait=False)
