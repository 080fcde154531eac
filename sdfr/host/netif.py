"""Facts about the local network interfaces, read from the kernel without extra dependencies."""

from __future__ import annotations

import fcntl
import re
import socket
import struct
from pathlib import Path

from sdfr.errors import ConfigError

_SYS = Path("/sys/class/net")
_SIOCGIFADDR = 0x8915
_SIOCGIFNETMASK = 0x891B


def exists(iface: str) -> bool:
    return (_SYS / iface).exists()


def default_iface() -> str:
    """The interface of the default route, else the first non-loopback one that is up."""
    try:
        for line in Path("/proc/net/route").read_text().splitlines()[1:]:
            cols = line.split()
            if len(cols) > 2 and cols[1] == "00000000":
                return cols[0]
    except OSError:
        pass
    for path in sorted(_SYS.iterdir()) if _SYS.exists() else []:
        if path.name == "lo":
            continue
        try:
            flags = int((path / "flags").read_text(), 16)
        except (OSError, ValueError):
            continue
        if flags & 0x1:  # IFF_UP
            return path.name
    raise ConfigError("iface: no interface given and none is up besides loopback; pass --iface")


def mac(iface: str) -> str:
    try:
        return (_SYS / iface / "address").read_text().strip().lower()
    except OSError:
        raise ConfigError(f"iface: no interface named {iface!r}") from None


def ipv4(iface: str, sock: socket.socket | None = None) -> str | None:
    """The interface's primary IPv4 address, or None when it has none. `sock` (any AF_INET
    socket) spares a caller that asks often a socket of its own each time."""
    if sock is None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            return ipv4(iface, s)
    try:
        res = fcntl.ioctl(sock.fileno(), _SIOCGIFADDR, struct.pack("256s", iface.encode()[:15]))
    except OSError:
        return None
    return socket.inet_ntoa(res[20:24])


def ipv4_network(iface: str, sock: socket.socket | None = None) -> str | None:
    """The interface's primary IPv4 subnet ("10.1.0.0/16"), or None when it has no address."""
    if sock is None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            return ipv4_network(iface, s)
    name = struct.pack("256s", iface.encode()[:15])
    try:
        addr = fcntl.ioctl(sock.fileno(), _SIOCGIFADDR, name)[20:24]
        mask = fcntl.ioctl(sock.fileno(), _SIOCGIFNETMASK, name)[20:24]
    except OSError:
        return None
    prefix = bin(int.from_bytes(mask, "big")).count("1")
    net = int.from_bytes(addr, "big") & int.from_bytes(mask, "big")
    return f"{socket.inet_ntoa(net.to_bytes(4, 'big'))}/{prefix}"


def index(iface: str) -> int:
    try:
        return socket.if_nametoindex(iface)
    except OSError:
        raise ConfigError(f"iface: no interface named {iface!r}") from None


def is_loopback(iface: str) -> bool:
    try:
        return bool(int((_SYS / iface / "flags").read_text(), 16) & 0x8)  # IFF_LOOPBACK
    except (OSError, ValueError):
        return False


def host_robot_id(hostname: str) -> str:
    """`hostname` as a robot id (A-Z a-z 0-9 . _ -, starting with a letter or digit, at most
    64 characters), or "" when nothing of it is left."""
    return re.sub(r"[^A-Za-z0-9._-]+", "-", hostname).strip("-._")[:64]


def robot_id_from_mac(iface: str) -> str:
    """The default robot id: stable for the hardware, readable (`robot-0242ac110002`); on an
    interface without a MAC address (lo), the host name (a first try on one machine)."""
    digits = mac(iface).replace(":", "")
    if digits and set(digits) != {"0"}:
        return f"robot-{digits}"
    host = host_robot_id(socket.gethostname())
    if not host:
        raise ConfigError(
            f"robot_id: {iface} has no MAC address and this machine no host name to derive an "
            "id from; pass --robot-id"
        )
    return host
