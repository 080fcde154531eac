"""Simulated 802.11 radios (the kernel's mac80211_hwsim), made and removed over generic netlink.

A radio is made in the initial network namespace (one made inside another namespace hears
only the radios of its own), then its phy is moved into a robot's namespace with `iw phy PHY
set netns name NS`, its interface renamed `wlan0` there (`kernel.adopt_radio`).  A radio of
netlab is named as its robot's namespace (``nl<lab>-<robot>``), so that what a lab made can be
found and removed again (`Hwsim.radios`, `release`) after the process that made it is gone.

The codec (`encode`, `decode`, `attrs`) is pure; `Genl` is the socket.  hwsim's interface is
its header, include/uapi/linux/... in the kernel sources as ``mac80211_hwsim.h``: the
commands and attributes below keep its numbers.
"""

from __future__ import annotations

import contextlib
import errno
import os
import socket
import struct
import subprocess
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from netlab import kernel
from netlab.errors import NetlabError, kernel_errors

_G = TypeVar("_G", bound="Genl")

NETLINK_GENERIC = 16
NLMSG_ERROR = 2
NLMSG_DONE = 3
NLM_F_REQUEST = 0x1
NLM_F_MULTI = 0x2
NLM_F_ACK = 0x4
NLM_F_DUMP = 0x300
GENL_ID_CTRL = 0x10
CTRL_CMD_GETFAMILY = 3
CTRL_ATTR_FAMILY_ID = 1
CTRL_ATTR_FAMILY_NAME = 2

FAMILY = "MAC80211_HWSIM"
VERSION = 1

# Commands (enum hwsim_commands)
CMD_REGISTER = 1
CMD_FRAME = 2
CMD_TX_INFO_FRAME = 3
CMD_NEW_RADIO = 4
CMD_DEL_RADIO = 5
CMD_GET_RADIO = 6

# Attributes (enum hwsim_attrs)
ATTR_ADDR_RECEIVER = 1
ATTR_ADDR_TRANSMITTER = 2
ATTR_FRAME = 3
ATTR_FLAGS = 4
ATTR_RX_RATE = 5
ATTR_SIGNAL = 6
ATTR_TX_INFO = 7
ATTR_COOKIE = 8
ATTR_CHANNELS = 9
ATTR_RADIO_ID = 10
ATTR_DESTROY_RADIO_ON_CLOSE = 16
ATTR_RADIO_NAME = 17
ATTR_FREQ = 19

_NLMSGHDR = struct.Struct("=IHHII")
_GENLHDR = struct.Struct("=BBH")
_NLATTR = struct.Struct("=HH")


def _align(n: int) -> int:
    return (n + 3) & ~3


def attr(kind: int, value: bytes) -> bytes:
    """One netlink attribute, padded to 4 bytes."""
    raw = _NLATTR.pack(_NLATTR.size + len(value), kind) + value
    return raw + b"\0" * (_align(len(raw)) - len(raw))


def attr_u32(kind: int, value: int) -> bytes:
    return attr(kind, struct.pack("=I", value))


def attr_str(kind: int, value: str) -> bytes:
    return attr(kind, value.encode() + b"\0")


def attrs(data: bytes) -> Iterator[tuple[int, bytes]]:
    """The (type, payload) of each attribute in `data`; a truncated one ends the walk."""
    at = 0
    while at + _NLATTR.size <= len(data):
        length, kind = _NLATTR.unpack_from(data, at)
        if length < _NLATTR.size or at + length > len(data):
            return
        yield kind & 0x3FFF, data[at + _NLATTR.size : at + length]  # (nested/byte-order bits)
        at += _align(length)


def encode(family: int, cmd: int, payload: bytes, seq: int, flags: int, version: int = 1) -> bytes:
    """A generic netlink request."""
    body = _GENLHDR.pack(cmd, version, 0) + payload
    return _NLMSGHDR.pack(_NLMSGHDR.size + len(body), family, flags, seq, 0) + body


@dataclass(frozen=True, slots=True)
class Message:
    """One netlink message read: its type, flags, sequence number and what follows the
    netlink header (for generic netlink: `cmd`, then `attributes`)."""

    kind: int
    flags: int
    seq: int
    body: bytes

    @property
    def error(self) -> int:
        """An NLMSG_ERROR's code: 0 an ack, < 0 -errno, > 0 a value some commands return."""
        return int(struct.unpack_from("=i", self.body)[0])

    @property
    def cmd(self) -> int:
        return self.body[0]

    @property
    def attributes(self) -> dict[int, bytes]:
        return dict(attrs(self.body[_GENLHDR.size :]))


def decode(data: bytes) -> Iterator[Message]:
    """The messages of one datagram read from a netlink socket."""
    at = 0
    while at + _NLMSGHDR.size <= len(data):
        length, kind, flags, seq, _pid = _NLMSGHDR.unpack_from(data, at)
        if length < _NLMSGHDR.size or at + length > len(data):
            return
        yield Message(kind, flags, seq, data[at + _NLMSGHDR.size : at + length])
        at += _align(length)


def cstr(value: bytes) -> str:
    return value.split(b"\0", 1)[0].decode(errors="replace")


class Genl:
    """A generic netlink socket of one family (resolved by name at open)."""

    def __init__(self, family_name: str = FAMILY) -> None:
        self.sock = socket.socket(socket.AF_NETLINK, socket.SOCK_RAW, NETLINK_GENERIC)
        self.sock.bind((0, 0))
        self._seq = 0
        try:
            reply = self.request(
                GENL_ID_CTRL, CTRL_CMD_GETFAMILY, attr_str(CTRL_ATTR_FAMILY_NAME, family_name)
            )
        except OSError as exc:
            self.sock.close()
            if exc.errno == errno.ENOENT:
                raise NetlabError(
                    f"no {family_name} generic netlink family: the mac80211_hwsim module is "
                    "not loaded (`modprobe mac80211_hwsim radios=0`; this host's kernel may "
                    "have no wireless stack: `netlab doctor`)"
                ) from None
            raise
        found = next((m for m in reply if CTRL_ATTR_FAMILY_ID in m.attributes), None)
        if found is None:
            self.sock.close()
            raise NetlabError(f"the kernel did not give {family_name}'s family id")
        self.family = int(struct.unpack_from("=H", found.attributes[CTRL_ATTR_FAMILY_ID])[0])

    def close(self) -> None:
        self.sock.close()

    def __enter__(self: _G) -> _G:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def request(self, family: int, cmd: int, payload: bytes = b"", flags: int = 0) -> list[Message]:
        """Send one request and read its answers up to its ack (or the dump's end).  An error
        raises OSError; an ack with a positive value is returned as that Message."""
        self._seq += 1
        seq = self._seq
        self.sock.send(
            encode(family, cmd, payload, seq, NLM_F_REQUEST | NLM_F_ACK | flags, VERSION)
        )
        out: list[Message] = []
        while True:
            for msg in decode(self.sock.recv(65536)):
                if msg.seq != seq:
                    continue
                if msg.kind == NLMSG_ERROR:
                    if msg.error < 0:
                        raise OSError(-msg.error, os.strerror(-msg.error))
                    if msg.error > 0:
                        out.append(msg)
                    return out
                if msg.kind == NLMSG_DONE:
                    return out
                out.append(msg)


@dataclass(frozen=True, slots=True)
class Radio:
    """One hwsim radio: its id (the kernel's index), its name (its phy's name) and, once
    read (`adopt`), the address hwsim knows it by: its permanent address with the 0x40 bit
    of the first octet set, which a medium names it with (`netlab.airmedium`)."""

    id: int
    name: str
    address: str = ""


class Hwsim(Genl):
    """mac80211_hwsim's control: make, list and remove radios."""

    def new_radio(self, name: str, *, destroy_on_close: bool = False) -> Radio:
        """A radio named `name`, in this socket's namespace, with one interface (wlanN)."""
        payload = attr_str(ATTR_RADIO_NAME, name) + attr_u32(ATTR_CHANNELS, 1)
        if destroy_on_close:
            payload += attr(ATTR_DESTROY_RADIO_ON_CLOSE, b"")
        try:
            reply = self.request(self.family, CMD_NEW_RADIO, payload)
        except OSError as exc:
            raise NetlabError(f"hwsim: cannot make radio {name!r}: {exc.strerror}") from None
        # The ack carries the new radio's index; the first radio's is 0, a plain ack.
        ids = [m.error for m in reply if m.kind == NLMSG_ERROR]
        return Radio(ids[0] if ids else 0, name)

    def radios(self) -> list[Radio]:
        """Every hwsim radio (of every namespace)."""
        out = []
        for msg in self.request(self.family, CMD_GET_RADIO, flags=NLM_F_DUMP):
            got: Mapping[int, bytes] = msg.attributes
            if ATTR_RADIO_ID in got and ATTR_RADIO_NAME in got:
                rid = int(struct.unpack_from("=I", got[ATTR_RADIO_ID])[0])
                out.append(Radio(rid, cstr(got[ATTR_RADIO_NAME])))
        return out

    def remove_radio(self, name: str) -> bool:
        """Remove the radio named `name`; False when there is none."""
        try:
            self.request(self.family, CMD_DEL_RADIO, attr_str(ATTR_RADIO_NAME, name))
        except OSError as exc:
            if exc.errno == errno.ENODEV:
                return False
            raise NetlabError(f"hwsim: cannot remove radio {name!r}: {exc.strerror}") from None
        return True


# -- radios in robots' namespaces ----------------------------------------------------------------

SYS_PHY = Path("/sys/class/ieee80211")
SYS_MODULE = Path("/sys/module/mac80211_hwsim")


def loaded(sys_module: Path = SYS_MODULE) -> bool:
    """Whether mac80211_hwsim is in the kernel (loaded, or built in)."""
    return sys_module.exists()


def phy_interfaces(phy: str, sys_phy: Path = SYS_PHY) -> list[str]:
    """The interfaces of radio `phy`, as this process's namespace sees them in sysfs."""
    net = sys_phy / phy / "device" / "net"
    try:
        return sorted(p.name for p in net.iterdir())
    except FileNotFoundError:
        return []


def _iw(argv: Sequence[str], doing: str, ns: str | None = None) -> None:
    if ns is not None:
        kernel.run_in_ns(ns, ["iw", *argv], doing)
        return
    with kernel_errors(doing):
        subprocess.run(
            ["iw", *argv],
            capture_output=True,
            text=True,
            timeout=30,
            check=True,
            stdin=subprocess.DEVNULL,
        )


def perm_address(phy: str, sys_phy: Path = SYS_PHY) -> str:
    """Radio `phy`'s permanent address, as this process's namespace sees it in sysfs."""
    with kernel_errors(f"reading the address of radio {phy}"):
        return (sys_phy / phy / "macaddress").read_text().strip()


def hwsim_address(perm: str) -> str:
    """The address hwsim knows a radio by (its second address): the permanent one with the
    0x40 bit of the first octet set."""
    first, _, rest = perm.partition(":")
    try:
        value = int(first, 16)
    except ValueError:
        raise NetlabError(f"not a MAC address: {perm!r}") from None
    return f"{value | 0x40:02x}:{rest}"


def adopt(hw: Hwsim, name: str, ns: str) -> tuple[Radio, str]:
    """A new radio named `name` moved into namespace `ns`: the radio (with its hwsim
    address) and its interface's name (the kernel's `wlanN`, unique on the machine:
    wpa_supplicant's control sockets, under one /run for every namespace, are named after
    it)."""
    radio = hw.new_radio(name)
    try:
        ifaces = phy_interfaces(name)
        if len(ifaces) != 1:
            raise NetlabError(f"hwsim radio {name!r} has interfaces {ifaces}, not one")
        radio = Radio(radio.id, radio.name, hwsim_address(perm_address(name)))
        _iw(["phy", name, "set", "netns", "name", ns], f"moving radio {name} into {ns}")
    except BaseException:
        hw.remove_radio(name)
        raise
    return radio, ifaces[0]


def release(hw: Hwsim, name: str, ns: str | None) -> bool:
    """Remove radio `name`, first bringing it back from namespace `ns` (the kernel removes a
    radio only from the namespace it is in); False when there was none."""
    if ns is not None and ns in kernel.list_ns():
        with contextlib.suppress(NetlabError):
            _iw(["phy", name, "set", "netns", "1"], f"moving radio {name} out of {ns}", ns)
    return hw.remove_radio(name)
