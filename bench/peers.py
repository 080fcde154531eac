"""The systems the side-by-side sets beside SDfR: one record each, what it takes to run its node
on a robot, what it sends (for the captures and its bytes) and the liveness knob it runs with.

A peer's node (`bench.peer_node`'s command line, churn, signals and event log) does SDfR's job
the way that system's users would.  A system may appear twice, once with its defaults and once
tuned for liveness where it offers a knob: the name says which (``zenoh-lease2s``), the knob
says how, and the two run apart (their own ports), so they never hear each other.
"""

from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import metadata

from bench.avahi_node import PROGRAMS as AVAHI_PROGRAMS
from bench.paper_lab import ROOT, SDFR_PORT
from bench.paper_measure import Flow

#: SDfR's own traffic: its beacons, announcements and replies, all on one UDP port.
SDFR_FLOWS: tuple[Flow, ...] = (("udp", SDFR_PORT),)


@dataclass(frozen=True, slots=True)
class Peer:
    """One system beside SDfR."""

    name: str  # its key in results and tables
    label: str  # what a table calls it (its version is added when it runs)
    module: str  # its node, run as `python -m MODULE` inside each robot
    flows: tuple[Flow, ...]  # all it sends and receives: the capture's filter and its bytes
    dist: str  # the distribution that provides it (for its version, and to say it is missing)
    imports: str  # the module its node imports
    knob: str = "its defaults"
    args: tuple[str, ...] = ()
    python: str | None = None  # its node's interpreter, in the checkout (else this one)
    setup: str | None = None  # the script that makes it runnable here (idempotent)
    programs: tuple[str, ...] = ()  # the programs its node runs (on PATH)
    version_argv: tuple[str, ...] = ()  # a command whose output ends with its version

    def interpreter(self) -> str:
        return str(ROOT / self.python) if self.python else sys.executable

    def missing(self) -> str | None:
        """Why its node cannot run here, or None."""
        absent = [p for p in self.programs if shutil.which(p) is None]
        if absent:
            return f"{self.label}: {', '.join(absent)} not installed (bash {self.setup})"
        if self.python is None:
            if importlib.util.find_spec(self.imports) is None:
                return f"{self.label}: {self.dist} is not installed (pip install -e '.[dev]')"
            return None
        probe = [self.interpreter(), "-c", f"import {self.imports}"]
        try:
            subprocess.run(probe, capture_output=True, check=True, timeout=60)
        except (OSError, subprocess.SubprocessError):
            return f"{self.label}: {self.python} cannot import {self.imports} (bash {self.setup})"
        return None

    def prepare(self) -> None:
        """Make its interpreter if it has a setup script and cannot run yet."""
        if self.setup is not None and self.missing() is not None:
            subprocess.run(["bash", self.setup], cwd=ROOT, check=True, stdin=subprocess.DEVNULL)

    def version(self) -> str:
        if self.version_argv:
            try:
                said = subprocess.run(self.version_argv, capture_output=True, text=True).stdout
            except OSError:
                return "?"
            return said.split()[-1] if said.split() else "?"
        if self.python is not None:
            ask = f"from importlib.metadata import version; print(version({self.dist!r}))"
            res = subprocess.run([self.interpreter(), "-c", ask], capture_output=True, text=True)
            return res.stdout.strip() or "?"
        try:
            return metadata.version(self.dist)
        except metadata.PackageNotFoundError:
            return "?"

    def argv(self, robot: str, ip: str, events: str, *common: str) -> list[str]:
        """Its node's command line for `robot` (`common`: the load's options, the same for
        every system)."""
        return [self.interpreter(), "-m", self.module, "--robot", robot, "--ip", ip,
                "--events", events, *common, *self.args]  # fmt: skip


#: IPv4 fragments after the first (a fragment offset that is not 0).
LATER_FRAGMENTS = "(ip[6:2] & 0x1fff != 0)"

#: The ROS 2 tier's interpreter (rclpy and Fast DDS from PyPI wheels) and what makes it.
ROS2_PYTHON = ".venv/ros2/bin/python"
ROS2_SETUP = "scripts/ros2-setup.sh"

PEERS: dict[str, Peer] = {
    p.name: p
    for p in (
        Peer("zeroconf", "python-zeroconf", "bench.zc_node", (("udp", 5353),), "zeroconf",
             "zeroconf"),
        Peer("zenoh", "Zenoh", "bench.zenoh_node", (("udp", 7446), ("tcp", 7447)),
             "eclipse-zenoh", "zenoh",
             knob="its defaults (transport lease 10 s)"),
        Peer("zenoh-lease2s", "Zenoh, lease 2 s", "bench.zenoh_node",
             (("udp", 7456), ("tcp", 7457)), "eclipse-zenoh", "zenoh",
             knob="transport/link/tx/lease = 2000 ms (keep-alive every 500 ms)",
             args=("--lease-ms", "2000", "--scout-port", "7456", "--listen-port", "7457")),
        # Avahi's port is python-zeroconf's: the two never run in one lab (`chosen`).
        Peer("avahi", "Avahi", "bench.avahi_node", (("udp", 5353),), "avahi-daemon",
             "bench.avahi_node", knob="its defaults (records' TTL: PTR and TXT 75 min)",
             setup="scripts/avahi-setup.sh",
             programs=AVAHI_PROGRAMS,
             version_argv=("avahi-daemon", "--version")),
        # Domain d: discovery multicast 7400 + 250 d (+1: user multicast), a participant's
        # own unicast + 10 and + 11 (one participant a robot: participant id 0).
        Peer("dds", "ROS 2 / Fast DDS", "bench.dds_node",
             (("udp", 7400), ("udp", 7401), ("udp", 7410), ("udp", 7411)), "ros_fastdds",
             "rclpy", knob="its defaults (participant lease 20 s, announced every 3 s)",
             python=ROS2_PYTHON, setup=ROS2_SETUP),
        Peer("dds-lease3s", "ROS 2 / Fast DDS, lease 3 s", "bench.dds_node",
             (("udp", 7650), ("udp", 7651), ("udp", 7660), ("udp", 7661)), "ros_fastdds",
             "rclpy", knob="participant leaseDuration 3 s, announced every 1 s (XML profile)",
             args=("--lease-s", "3", "--domain", "1"), python=ROS2_PYTHON, setup=ROS2_SETUP),
    )
}  # fmt: skip
#: What the side-by-side runs unless told otherwise.
DEFAULT = ("zeroconf", "zenoh")


def chosen(names: Sequence[str]) -> list[Peer]:
    """The peers named, each known and runnable here; else ValueError saying which is not."""
    out: list[Peer] = []
    taken: dict[Flow, str] = dict.fromkeys(SDFR_FLOWS, "sdfr")
    for name in names:
        peer = PEERS.get(name)
        if peer is None:
            raise ValueError(f"no peer {name!r}: the side-by-side knows {', '.join(PEERS)}")
        shared = sorted(f for f in peer.flows if f in taken)
        if shared:
            ports = ", ".join(f"{proto} {port}" for proto, port in shared)
            raise ValueError(f"{name} and {taken[shared[0]]} cannot run in one lab: both use "
                             f"{ports} (their traffic could not be told apart)")  # fmt: skip
        taken.update(dict.fromkeys(peer.flows, name))
        peer.prepare()
        why = peer.missing()
        if why is not None:
            raise ValueError(why)
        out.append(peer)
    return out


def capture_filter(flows: Sequence[Flow]) -> str:
    """A pcap filter for these flows, and every later IP fragment (a fragment after the first
    has no UDP header to match a port: `paper_measure.ip_traffic` ties it to its datagram)."""
    return " or ".join([*(f"{proto} port {port}" for proto, port in flows), LATER_FRAGMENTS])
