"""The paper's traffic figure (its figure 6): the measure a run's report gives beside it, and
the conditions under which a run's figures may be set beside the paper's.

`paper_measure` gives TX and RX kilobytes per robot (UDP payload and whole frame) and the same
scaled to the paper's 5-minute runs; `run_conditions` states a run's robots, length, beacon
and services, and `RunConditions.paper_differences` how they differ from the paper's.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from netlab.analysis import traffic_per_robot, transmissions
from netlab.pcap import SDFR, Record
from sdfr.protocol.config import CoreConfig

__all__ = [
    "PAPER_BEACON_S",
    "PAPER_CONDITIONS",
    "PAPER_ROBOTS",
    "PAPER_RX_KB_5MIN",
    "PAPER_SERVICES_PER_ROBOT",
    "PAPER_TX_KB_5MIN",
    "RunConditions",
    "beacon_period",
    "paper_measure",
    "published_services",
    "run_conditions",
]

#: The paper's figure 6: kilobytes per robot over a 5-minute run (2 to 6 robots, static and
#: moving fleets).
PAPER_TX_KB_5MIN = (220, 320)
PAPER_RX_KB_5MIN = (540, 850)
FIVE_MINUTES_S = 300.0
#: The conditions of those figures: the default 10 s beacon, 2 to 6 robots, each with 100
#: simulated services of which 30, 50 or 70 % were published, runs of 5 minutes.
PAPER_BEACON_S = 10.0
PAPER_ROBOTS = (2, 6)
PAPER_SERVICES_PER_ROBOT = (30, 70)
PAPER_CONDITIONS = "10 s beacon, 2-6 robots, 30-70 services each, 5 min runs"
#: sdfrd draws each gap between its beacons from (1 - this) to 1 times its period.
_BEACON_JITTER = CoreConfig(fleet=1, robot_id="-").jitter


def paper_measure(records: Iterable[Record], *, duration: float | None = None) -> dict[str, Any]:
    """The paper's measure: TX and RX kilobytes per robot over the run, in JSON form.

    Both sizes are given (UDP payload and whole frame), plus the same rate over 5 minutes, the
    paper's run length, when the run's `duration` (default: first to last record) is known.
    """
    recs = list(records)
    if duration is None:
        times = [r.time for r in recs if r.kind == SDFR]
        duration = (max(times) - min(times)) if times else 0.0
    scale = FIVE_MINUTES_S / duration if duration > 0 else None
    robots: dict[str, Any] = {}
    for robot, t in traffic_per_robot(recs).items():
        entry: dict[str, Any] = {
            "tx": t.tx.to_json(),
            "rx": t.rx.to_json(),
            "tx_kB": {"payload": t.tx.payload_bytes / 1000, "frame": t.tx.frame_bytes / 1000},
            "rx_kB": {"payload": t.rx.payload_bytes / 1000, "frame": t.rx.frame_bytes / 1000},
        }
        if scale is not None:
            entry["per_5_min_kB"] = {
                f"{d}_{s}": round(entry[f"{d}_kB"][s] * scale, 3)
                for d in ("tx", "rx")
                for s in ("payload", "frame")
            }
        robots[robot] = entry
    return {
        "definition": (
            "TX: SDfR datagrams (UDP port 1900) a robot sent, by the robot id in them; RX: "
            "those that reached the robot's interface. payload = UDP payload bytes; frame = "
            "whole Ethernet frame as captured (headers included, no preamble/FCS). "
            "1 kB = 1000 bytes. ARP is not included."
        ),
        "duration_s": duration,
        "robots": robots,
        "paper_5_min_kB": {"tx": list(PAPER_TX_KB_5MIN), "rx": list(PAPER_RX_KB_5MIN)},
    }


@dataclass(frozen=True, slots=True)
class RunConditions:
    """What a run's traffic was measured under: robots, the run's length, the beacon period
    and the services each robot published (lowest, highest); None: not known."""

    robots: int
    duration_s: float
    beacon_s: float | None
    services_per_robot: tuple[int, int] | None

    def describe(self) -> str:
        """'3 robots, 1 s beacon, 2 services each, 6.8 s'."""
        beacon = "beacon unknown" if self.beacon_s is None else f"{self.beacon_s:g} s beacon"
        services = "services unknown" if self.services_per_robot is None else self._services()
        each = "" if self.services_per_robot is None else " each"
        return (
            f"{_count(self.robots, 'robot')}, {beacon}, {services}{each}, "
            f"{_seconds(self.duration_s)} s"
        )

    def paper_differences(self) -> list[str]:
        """How this run differs from the runs of the paper's figure 6 (`PAPER_*`);
        empty when it does not, and only then may its figures be set beside the paper's."""
        out = []
        if self.beacon_s is None:
            out.append("beacon unknown")
        elif not math.isclose(self.beacon_s, PAPER_BEACON_S):
            out.append(f"a {self.beacon_s:g} s beacon")
        low, high = PAPER_ROBOTS
        if not low <= self.robots <= high:
            out.append(_count(self.robots, "robot"))
        least, most = PAPER_SERVICES_PER_ROBOT
        if self.services_per_robot is None:
            out.append("services per robot unknown")
        elif not (least <= self.services_per_robot[0] and self.services_per_robot[1] <= most):
            out.append(f"{self._services()} per robot")
        # 5 minutes, give or take a beacon (a run's window starts with its captures).
        if self.duration_s < FIVE_MINUTES_S - PAPER_BEACON_S:
            out.append(f"a {_seconds(self.duration_s)} s run")
        return out

    def _services(self) -> str:
        assert self.services_per_robot is not None
        low, high = self.services_per_robot
        return _count(low, "service") if low == high else f"{low}-{high} services"

    def to_json(self) -> dict[str, object]:
        services = self.services_per_robot
        return {
            "robots": self.robots,
            "duration_s": self.duration_s,
            "beacon_s": self.beacon_s,
            "services_per_robot": None if services is None else list(services),
        }


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


def _seconds(value: float) -> str:
    """300, 60, 6.8: whole seconds from 100 s on, else one decimal unless it is 0."""
    text = f"{value:.0f}" if value >= 100 else f"{value:.1f}"
    return text.removesuffix(".0")


def run_conditions(
    meta: Mapping[str, Any], recs: Sequence[Record], *, robots: int, duration: float
) -> RunConditions:
    """The conditions of a run: its beacon (`beacon_period`) and the services each of its
    `robots` published, as `meta` states them (``services_per_robot``: a number, or
    [lowest, highest]) or else as the latest complete Update of each robot counted them."""
    stated = meta.get("services_per_robot")
    services: tuple[int, int] | None
    if stated is not None:
        low, high = (stated, stated) if isinstance(stated, int | float) else stated
        services = (int(low), int(high))
    else:
        counts = published_services(recs)
        enough = counts and len(counts) >= robots
        services = (min(counts.values()), max(counts.values())) if enough else None
    return RunConditions(robots, duration, beacon_period(meta, recs), services)


def published_services(recs: Iterable[Record]) -> dict[str, int]:
    """Robot -> how many services its latest complete Update (every part seen) listed."""
    parts: dict[tuple[str, int | None, int | None], dict[int, int]] = {}
    size: dict[tuple[str, int | None, int | None], int] = {}
    when: dict[tuple[str, int | None, int | None], float] = {}
    for r in recs:
        if r.msg_type != "Update" or r.robot is None or r.services is None:
            continue
        key = (r.robot, r.boot, r.version)
        parts.setdefault(key, {})[r.part or 0] = r.services
        size[key] = r.parts or 1
        when[key] = max(when.get(key, r.time), r.time)
    latest: dict[str, tuple[float, int]] = {}
    for key, seen in parts.items():
        if len(seen) >= size[key] and when[key] >= latest.get(key[0], (-math.inf, 0))[0]:
            latest[key[0]] = (when[key], sum(seen.values()))
    return {robot: count for robot, (_t, count) in sorted(latest.items())}


def beacon_period(meta: Mapping[str, Any], recs: Iterable[Record]) -> float | None:
    """The run's beacon period in seconds: ``beacon_interval_s`` in `meta`, else the one that
    the gaps between each robot's Alive datagrams were drawn from (two significant digits);
    None: neither is known."""
    stated = meta.get("beacon_interval_s")
    if stated is not None:
        if isinstance(stated, bool) or not isinstance(stated, int | float) or stated <= 0:
            raise ValueError(
                f"beacon_interval_s must be a positive number of seconds, not {stated!r}"
            )
        return float(stated)
    last: dict[str, float] = {}
    gaps = []
    for r in transmissions(recs):
        if r.msg_type == "Alive" and r.robot is not None:
            if r.robot in last:
                gaps.append(r.time - last[r.robot])
            last[r.robot] = r.time
    if not gaps:
        return None
    # sdfrd draws each gap from (1 - jitter) to 1 times its period: the median is the middle.
    return float(f"{statistics.median(gaps) / (1 - _BEACON_JITTER / 2):.2g}")
