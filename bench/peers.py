"""The systems the side-by-side sets beside SDfR: one record each, what it takes to run its node
on a robot, what it sends (for the captures and its bytes) and the liveness knob it runs with.

A peer's node (`bench.peer_node`'s command line, churn, signals and event log) does SDfR's job
the way that system's users would.  A system may appear twice, once with its defaults and once
tuned for liveness where it offers a knob: the name says which (``zenoh-lease2s``), the knob
says how, and the two run apart (their own ports), so they never hear each other.
"""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import metadata

from bench.paper_lab import SDFR_PORT
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

    def missing(self) -> str | None:
        """Why its node cannot run here, or None."""
        if importlib.util.find_spec(self.imports) is None:
            return f"{self.label}: {self.dist} is not installed (pip install -e '.[dev]')"
        return None

    def version(self) -> str:
        try:
            return metadata.version(self.dist)
        except metadata.PackageNotFoundError:
            return "?"

    def argv(self, robot: str, ip: str, events: str, *common: str) -> list[str]:
        """Its node's command line for `robot` (`common`: the load's options, the same for
        every system)."""
        return [sys.executable, "-m", self.module, "--robot", robot, "--ip", ip,
                "--events", events, *common, *self.args]  # fmt: skip


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
    )
}  # fmt: skip
#: What the side-by-side runs unless told otherwise.
DEFAULT = ("zeroconf", "zenoh")


def chosen(names: Sequence[str]) -> list[Peer]:
    """The peers named, each known and runnable here; else ValueError saying which is not."""
    out = []
    for name in names:
        peer = PEERS.get(name)
        if peer is None:
            raise ValueError(f"no peer {name!r}: the side-by-side knows {', '.join(PEERS)}")
        why = peer.missing()
        if why is not None:
            raise ValueError(why)
        out.append(peer)
    return out


def capture_filter(flows: Sequence[Flow]) -> str:
    """A pcap filter for these flows."""
    return " or ".join(f"{proto} port {port}" for proto, port in flows)
