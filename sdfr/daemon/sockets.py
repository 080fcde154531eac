"""The discovery layer's socket on the fleet's network, and the one timer each of its machines
(the protocol core, the address machine) keeps."""

from __future__ import annotations

import asyncio
import socket
import struct
from collections.abc import Callable

from sdfr.config.load import Config
from sdfr.errors import SdfrError
from sdfr.host import netif


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


def rearm(
    loop: asyncio.AbstractEventLoop,
    timer: asyncio.TimerHandle | None,
    deadline: float | None,
    callback: Callable[[], None],
) -> asyncio.TimerHandle | None:
    """A machine's one timer, set for its next `deadline` (monotonic; None: no timer): `timer`
    when it is already set for it, else cancelled and set anew. (loop.time() is
    time.monotonic() on Linux's default loop.)"""
    if timer is not None and (deadline is None or timer.when() != deadline):
        timer.cancel()
        timer = None
    if deadline is not None and timer is None:
        timer = loop.call_at(deadline, callback)
    return timer
