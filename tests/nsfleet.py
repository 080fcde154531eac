"""A small fleet of network namespaces for integration tests.

``NsFleet(name, n)`` builds, with pyroute2 (no ``ip`` commands for set-up):

* ``<name>-air``: the "medium" namespace holding the bridge ``br0``.  The
  bridge does not live in the root namespace because, once Docker has run on
  a machine, a root-namespace bridge silently drops bridged traffic.
* ``<name>-r1`` .. ``<name>-rN``: one namespace per robot, with ``lo`` up and
  ``eth0`` (address ``<subnet>.<i>``, MAC ``02:00:00:00:00:<i>``) joined by a
  veth pair to the air-side port ``v<i>`` enslaved to ``br0``, plus a route
  ``224.0.0.0/4 dev eth0`` so that multicast works without a default route.

Processes are started inside a robot with ``popen``/``exec`` (``ip netns
exec``).  Leaving the context (or a failure half-way through set-up) stops
every recorded process group and deletes exactly the namespaces this object
created; nothing is matched by pattern.

This module is a test helper; the full testbed (shaping, partitions,
captures) is ``netlab``.
"""

from __future__ import annotations

import contextlib
import errno
import ipaddress
import itertools
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

from pyroute2 import IPRoute, netns

from netlab.naming import b36
from sdfr import procfs

PREFIX = "sdfr"
ROBOT_IFACE = "eth0"
BRIDGE = "br0"
MCAST_ROUTE = "224.0.0.0/4"
TERM_GRACE_S = 3.0
_RT_SCOPE_LINK = 253

_counter = itertools.count()
_counter_lock = threading.Lock()


def name_pid(name: str) -> int | None:
    """The pid encoded by ``unique_name`` in ``name``, or None if not ours."""
    if not name.startswith(PREFIX) or len(name) < len(PREFIX) + 6:
        return None
    try:
        return int(name[len(PREFIX) : len(PREFIX) + 5], 36)
    except ValueError:
        return None


def unique_name() -> str:
    """A fleet name unique on this machine: ``sdfr`` + pid (5 base-36 digits)
    + a counter, e.g. ``sdfr00b3k0`` (10 characters for the first 36 fleets
    of a process).  Names whose namespaces already exist are skipped."""
    taken = set(netns.listnetns())
    while True:
        with _counter_lock:
            count = next(_counter)
        name = f"{PREFIX}{b36(os.getpid(), 5)}{b36(count)}"
        if not any(ns == f"{name}-air" or ns.startswith(f"{name}-r") for ns in taken):
            return name


def default_mac(i: int) -> str:
    return f"02:00:00:00:{(i >> 8) & 0xFF:02x}:{i & 0xFF:02x}"


class NsFleet:
    """``n`` robot namespaces on one bridged medium.  Robots are numbered 1..n."""

    def __init__(
        self,
        name: str,
        n: int,
        subnet: str = "10.1.0.0/16",
        macs: Sequence[str] | None = None,
    ) -> None:
        net = ipaddress.IPv4Network(subnet)
        if not 1 <= n < net.num_addresses - 1:
            raise ValueError(f"n={n} robots do not fit in {subnet}")
        if macs is not None and len(macs) != n:
            raise ValueError(f"{len(macs)} MACs given for {n} robots")
        self.name = name
        self.n = n
        self.subnet = net
        self.air = f"{name}-air"
        self._macs = list(macs) if macs is not None else [default_mac(i) for i in range(1, n + 1)]
        self._created: list[str] = []  # namespaces made by this object, in order
        self._procs: list[tuple[int, subprocess.Popen[Any]]] = []
        self._air: IPRoute | None = None
        self._closed = False
        self.setup_seconds = 0.0

    # -- naming -------------------------------------------------------------
    def ns(self, i: int) -> str:
        self._check(i)
        return f"{self.name}-r{i}"

    def address(self, i: int) -> str:
        self._check(i)
        return str(self.subnet.network_address + i)

    def mac(self, i: int) -> str:
        self._check(i)
        return self._macs[i - 1]

    def air_port(self, i: int) -> str:
        self._check(i)
        return f"v{i}"

    @property
    def namespaces(self) -> list[str]:
        """Every namespace name this fleet owns (created or to be created)."""
        return [self.air] + [self.ns(i) for i in range(1, self.n + 1)]

    def _check(self, i: int) -> None:
        if not 1 <= i <= self.n:
            raise IndexError(f"robot {i} not in 1..{self.n}")

    # -- life cycle ---------------------------------------------------------
    def __enter__(self) -> NsFleet:
        try:
            self.setup()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def _new_ns(self, name: str) -> IPRoute:
        """Create namespace ``name`` (it must not exist) and return a socket in it."""
        if name in netns.listnetns():
            raise FileExistsError(f"network namespace {name} already exists")
        # Recorded before the call: if creation fails half-way, close() removes
        # the mount point; it did not exist a moment ago, so it is ours.
        self._created.append(name)
        try:
            return IPRoute(netns=name, flags=os.O_CREAT | os.O_EXCL)
        except OSError as e:
            if e.errno == errno.EEXIST:  # someone else made it in the meantime
                self._created.remove(name)
            raise

    def setup(self) -> None:
        if self._created:
            raise RuntimeError("fleet already set up")
        t0 = time.perf_counter()
        air = self._air = self._new_ns(self.air)
        air.link("set", index=air.link_lookup(ifname="lo")[0], state="up")
        # No multicast snooping: the medium floods multicast like a radio,
        # regardless of IGMP membership timers.
        air.link("add", ifname=BRIDGE, kind="bridge", br_mcast_snooping=0, state="up")
        bridge = air.link_lookup(ifname=BRIDGE)[0]
        for i in range(1, self.n + 1):
            ns = self.ns(i)
            with self._new_ns(ns) as robot:
                air.link(
                    "add",
                    ifname=self.air_port(i),
                    kind="veth",
                    master=bridge,
                    state="up",
                    peer={"ifname": ROBOT_IFACE, "net_ns_fd": ns, "address": self.mac(i)},
                )
                robot.link("set", index=robot.link_lookup(ifname="lo")[0], state="up")
                eth = robot.link_lookup(ifname=ROBOT_IFACE)[0]
                robot.addr(
                    "add", index=eth, address=self.address(i), prefixlen=self.subnet.prefixlen
                )
                robot.link("set", index=eth, state="up")
                robot.route("add", dst=MCAST_ROUTE, oif=eth, scope=_RT_SCOPE_LINK)
        self.setup_seconds = time.perf_counter() - t0

    def close(self) -> None:
        """Stop recorded processes, then delete the namespaces made here.  Idempotent."""
        if self._closed:
            return
        self._closed = True
        errors: list[str] = []
        try:
            self._stop_all()
        except Exception as e:  # keep going: the namespaces must go anyway
            errors.append(f"stopping processes: {e!r}")
        if self._air is not None:
            with contextlib.suppress(Exception):
                self._air.close()
            self._air = None
        existing = set(netns.listnetns())
        for name in reversed(self._created):
            if name not in existing:
                continue
            try:
                netns.remove(name)
            except FileNotFoundError:
                pass
            except OSError as e:
                errors.append(f"removing {name}: {e!r}")
        self._created.clear()
        if errors:
            raise RuntimeError(f"NsFleet {self.name} teardown: " + "; ".join(errors))

    # -- processes ----------------------------------------------------------
    def _cmd(self, i: int, argv: Sequence[str]) -> list[str]:
        if isinstance(argv, str):
            raise TypeError("argv must be a sequence of strings, not a string")
        return ["ip", "netns", "exec", self.ns(i), *argv]

    def popen(self, i: int, argv: Sequence[str], **kw: Any) -> subprocess.Popen[Any]:
        """Start ``argv`` inside robot ``i`` in a new session (own process group).

        Keyword arguments go to ``subprocess.Popen``; stdin defaults to
        /dev/null.  The process is stopped when the fleet closes."""
        if self._closed:
            raise RuntimeError("fleet is closed")
        if "process_group" in kw or kw.get("start_new_session", True) is not True:
            raise ValueError("fleet processes always run in their own session")
        kw.setdefault("stdin", subprocess.DEVNULL)
        kw["start_new_session"] = True
        proc: subprocess.Popen[Any] = subprocess.Popen(self._cmd(i, argv), **kw)
        self._procs.append((i, proc))
        return proc

    def sdfrd(
        self, i: int, state_dir: Path, log: Path, beacon: float, *extra: str
    ) -> subprocess.Popen[Any]:
        """Start sdfrd in robot ``i`` (on eth0, fleet 1, robot id ``r<i>``) with that state
        directory and beacon, and ``extra`` flags; its output is appended to ``log``."""
        argv = [
            sys.executable, "-m", "sdfr.daemon.supervisor", "--iface", "eth0", "--fleet", "1",
            "--robot-id", f"r{i}", "--state-dir", str(state_dir),
            "--beacon-interval", str(beacon), *extra,
        ]  # fmt: skip
        with open(log, "ab") as out:
            return self.popen(i, argv, stdout=out, stderr=subprocess.STDOUT)

    def exec(self, i: int, argv: Sequence[str], **kw: Any) -> subprocess.CompletedProcess[Any]:
        """Run ``argv`` inside robot ``i`` to completion (text output captured,
        30 s timeout, no check; all overridable)."""
        kw.setdefault("stdin", subprocess.DEVNULL)
        if "stdout" not in kw and "stderr" not in kw:
            kw.setdefault("capture_output", True)
        kw.setdefault("text", True)
        kw.setdefault("timeout", 30)
        return subprocess.run(self._cmd(i, argv), **kw)

    def processes(self, i: int | None = None) -> list[subprocess.Popen[Any]]:
        return [p for j, p in self._procs if i is None or i == j]

    def kill(self, target: int | subprocess.Popen[Any], sig: int = signal.SIGTERM) -> None:
        """Send ``sig`` to the process group of one recorded process, or of
        every recorded process of robot ``target``, if it is still running."""
        if isinstance(target, int):
            procs = self.processes(target)
        else:
            if all(p is not target for _, p in self._procs):
                raise ValueError("not a process started by this fleet")
            procs = [target]
        for p in procs:
            if p.poll() is None:
                _signal_group(p, sig)

    def _stop_all(self) -> None:
        procs = [p for _, p in self._procs]
        for p in procs:
            if p.poll() is None:
                _signal_group(p, signal.SIGTERM)
        deadline = time.monotonic() + TERM_GRACE_S
        for p in procs:
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(timeout=max(0.0, deadline - time.monotonic()))
        for p in procs:
            if p.poll() is None:
                _signal_group(p, signal.SIGKILL)
                p.wait()
        self._procs.clear()
        # Whatever is still inside one of our namespaces (a child left behind
        # by a leader that exited, something started by hand with
        # `ip netns exec`) is ours by definition: kill it by pid.
        self._kill_inside()

    def _kill_inside(self) -> None:
        ours = set(self._created)
        left = [pid for ns, pids in netns.ns_pids().items() if ns in ours for pid in pids]
        for pid in left:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, signal.SIGKILL)
        deadline = time.monotonic() + TERM_GRACE_S
        while left and time.monotonic() < deadline:
            left = [pid for pid in left if _running(pid)]
            if left:
                time.sleep(0.02)

    # -- links --------------------------------------------------------------
    def _air_link(self, i: int, state: str) -> None:
        if self._air is None:
            raise RuntimeError("fleet is not set up")
        port = self._air.link_lookup(ifname=self.air_port(i))[0]
        self._air.link("set", index=port, state=state)

    def cut(self, i: int) -> None:
        """Cut robot ``i`` off the medium (its air-side port goes down)."""
        self._air_link(i, "down")

    def restore(self, i: int) -> None:
        """Put robot ``i`` back on the medium."""
        self._air_link(i, "up")


def _signal_group(proc: subprocess.Popen[Any], sig: int) -> None:
    # Only called while the leader is not reaped: its pid is the group id
    # (start_new_session) and cannot have been reused.
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, sig)


_running = procfs.running
