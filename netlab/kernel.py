"""Thin wrappers over namespaces and commands run inside them; errors come out as KernelError."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
from collections.abc import Iterator, Sequence
from ipaddress import IPv4Interface
from pathlib import Path

from pyroute2 import IPRoute, netns

from netlab.errors import KernelError, kernel_errors

NETNS_DIR = Path("/run/netns")
RT_SCOPE_LINK = 253


def list_ns(prefix: str = "") -> list[str]:
    return sorted(ns for ns in netns.listnetns() if ns.startswith(prefix))


def create_ns(name: str) -> IPRoute:
    """Create namespace `name` (it must not exist) and return a netlink socket inside it."""
    with kernel_errors(f"creating network namespace {name}"):
        return IPRoute(netns=name, flags=os.O_CREAT | os.O_EXCL)


def attach_ns(name: str, pid: int) -> None:
    """Name the network namespace of process `pid` `name` (as `ip netns attach` does): a
    container's namespace then serves as a lab's like one netlab made."""
    if name in netns.listnetns():
        raise KernelError(f"network namespace {name} exists already")
    with kernel_errors(f"naming the network namespace of process {pid} {name}"):
        netns.attach(name, pid)


def open_ns(name: str) -> IPRoute:
    """A netlink socket inside the existing namespace `name`."""
    if name not in netns.listnetns():
        raise KernelError(f"network namespace {name} does not exist (was the lab taken down?)")
    with kernel_errors(f"opening network namespace {name}"):
        return IPRoute(netns=name, flags=0)


def addresses(name: str, ifname: str, doing: str) -> list[str]:
    """The IPv4 addresses interface `ifname` of namespace `name` has right now."""
    ipr = open_ns(name)
    try:
        with kernel_errors(doing):
            index = ipr.link_lookup(ifname=ifname)[0]
            found = ipr.get_addr(family=socket.AF_INET, index=index)
            return [str(a.get_attr("IFA_ADDRESS")) for a in found]
    finally:
        ipr.close()


def remove_ns(name: str) -> bool:
    """Delete namespace `name`; False if it was already gone."""
    if name not in netns.listnetns():
        return False
    try:
        netns.remove(name)
    except FileNotFoundError:
        return False
    except OSError as exc:
        raise KernelError(f"removing network namespace {name} failed: {exc.strerror}") from exc
    return True


def ns_inode(name: str) -> tuple[int, int] | None:
    """(device, inode) identifying namespace `name`, or None if it does not exist."""
    try:
        st = os.stat(NETNS_DIR / name)
    except OSError:
        return None
    return (st.st_dev, st.st_ino)


@contextlib.contextmanager
def inside(name: str) -> Iterator[None]:
    """Run the body with this thread in namespace `name` (for /proc/sys/net writes)."""
    with kernel_errors(f"entering network namespace {name}"):
        netns.pushns(name)
    try:
        yield
    finally:
        netns.popns()


def set_sysctl(key: str, value: str) -> None:
    """Write a /proc/sys value in the current thread's network namespace."""
    path = Path("/proc/sys") / key.replace(".", "/")
    with kernel_errors(f"setting {key}"):
        path.write_text(value)


def ipv4_only(name: str) -> None:
    """Turn IPv6 off in namespace `name`, for every interface made in it afterwards too."""
    with inside(name):
        set_sysctl("net.ipv6.conf.all.disable_ipv6", "1")
        set_sysctl("net.ipv6.conf.default.disable_ipv6", "1")


def bring_up(
    name: str, ifname: str, address: IPv4Interface | None, doing: str, mtu: int | None = None
) -> None:
    """Bring up lo and `ifname` of namespace `name`, give `ifname` `address` (None: none),
    its `mtu` (None: as it is) and the link-scope multicast route: without a default route a
    namespace cannot send or join multicast."""
    ipr = open_ns(name)
    try:
        with kernel_errors(doing):
            ipr.link("set", index=ipr.link_lookup(ifname="lo")[0], state="up")
            index = ipr.link_lookup(ifname=ifname)[0]
            if address is not None:
                ipr.addr(
                    "add", index=index, address=str(address.ip), prefixlen=address.network.prefixlen
                )
            if mtu is not None:
                ipr.link("set", index=index, mtu=mtu)
            ipr.link("set", index=index, state="up")
            ipr.route("add", dst="224.0.0.0/4", oif=index, scope=RT_SCOPE_LINK)
    finally:
        ipr.close()


def ns_argv(name: str, argv: Sequence[str]) -> list[str]:
    """`argv` run inside namespace `name` (with its own /sys, as tools expect)."""
    if isinstance(argv, str):
        raise TypeError("argv must be a sequence of strings, not a string")
    return ["ip", "netns", "exec", name, *argv]


def run_in_ns(name: str, argv: Sequence[str], doing: str, stdin: str | None = None) -> str:
    """Run `argv` in namespace `name` to completion; its stdout, or KernelError with stderr."""
    return run_argv(ns_argv(name, argv), doing, stdin)


def run_argv(argv: Sequence[str], doing: str, stdin: str | None = None) -> str:
    """Run `argv` in this process's own namespace to completion; its stdout, or KernelError
    with stderr."""
    with kernel_errors(doing):
        res = subprocess.run(
            list(argv),
            input=stdin,
            capture_output=True,
            text=True,
            timeout=60,
            check=True,
            stdin=None if stdin is not None else subprocess.DEVNULL,
        )
    return res.stdout
