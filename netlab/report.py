"""A run's report: ``report.json`` (figures) and PNG plots, written into the run's folder.

`write_report(run_dir, records=...)` takes the records of the run's captures
(`netlab.analysis.read_run`) and, when the scenario sampled them, connectivity and
neighbour-table agreement over time.  All times are UNIX seconds (``time.time()``), the clock
of the pcaps; plots show seconds since the start of the run.

Plots (drawn by `netlab.plots`):

* ``bytes_per_robot.png``: kilobytes each robot sent (TX) and received (RX), as whole frames
  and as UDP payload;
* ``datagrams_per_type.png``: datagrams per second sent on the air, per message type;
* ``connectivity.png`` (with connectivity samples): linked pairs on the medium and reachable
  peers per robot over time;
* ``agreement.png`` (with agreement samples): how far neighbour tables agree with the
  medium's true connectivity over time.
"""

from __future__ import annotations

import json
import math
import statistics
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from netlab import analysis
from netlab import plots as draw
from netlab.analysis import Record
from netlab.capture import CaptureInfo
from sdfr.protocol.config import CoreConfig

__all__ = [
    "AGREEMENT_TARGET",
    "REPORT_JSON",
    "AgreementSample",
    "ConnectivitySample",
    "RunConditions",
    "beacon_period",
    "published_services",
    "run_conditions",
    "write_report",
]

REPORT_JSON = "report.json"
SCHEMA = "netlab-report/1"
#: Share of the time neighbour lists must agree with the truth (issue: mobility check).
AGREEMENT_TARGET = 0.95
#: sdfrd draws each gap between its beacons from (1 - this) to 1 times its period.
_BEACON_JITTER = CoreConfig(fleet=1, robot_id="-").jitter


@dataclass(frozen=True, slots=True)
class ConnectivitySample:
    """The fleet's connectivity at one moment.

    linked_pairs: unordered robot pairs the medium links (ground truth);
    reachable: per robot, how many peers its neighbour list says are reachable;
    reachable_pairs: unordered pairs in which both robots list each other (optional).
    """

    time: float
    linked_pairs: int
    reachable: Mapping[str, int] = field(default_factory=dict)
    reachable_pairs: int | None = None

    @classmethod
    def coerce(cls, obj: ConnectivitySample | Mapping[str, Any]) -> ConnectivitySample:
        if isinstance(obj, ConnectivitySample):
            return obj
        rp = obj.get("reachable_pairs")
        return cls(
            time=float(obj["time"] if "time" in obj else obj["t"]),
            linked_pairs=int(obj["linked_pairs"]),
            reachable={str(k): int(v) for k, v in dict(obj.get("reachable") or {}).items()},
            reachable_pairs=None if rp is None else int(rp),
        )

    def to_json(self) -> dict[str, object]:
        out: dict[str, Any] = {
            "time": self.time,
            "linked_pairs": self.linked_pairs,
            "reachable": dict(self.reachable),
        }
        if self.reachable_pairs is not None:
            out["reachable_pairs"] = self.reachable_pairs
        return out


@dataclass(frozen=True, slots=True)
class AgreementSample:
    """Neighbour tables against the medium's truth at one moment.

    agreement: 0..1, share of ordered (robot, peer) pairs on which they agree (see
    `netlab.analysis.neighbour_agreement`); per_robot: the same per robot (optional).
    """

    time: float
    agreement: float
    per_robot: Mapping[str, float] = field(default_factory=dict)

    @classmethod
    def coerce(cls, obj: AgreementSample | Mapping[str, Any]) -> AgreementSample:
        if isinstance(obj, AgreementSample):
            return obj
        value = float(obj["agreement"])
        if not 0.0 <= value <= 1.0:
            raise ValueError(f"agreement must be within 0..1, not {value}")
        return cls(
            time=float(obj["time"] if "time" in obj else obj["t"]),
            agreement=value,
            per_robot={str(k): float(v) for k, v in dict(obj.get("per_robot") or {}).items()},
        )

    def to_json(self) -> dict[str, object]:
        out: dict[str, Any] = {"time": self.time, "agreement": self.agreement}
        if self.per_robot:
            out["per_robot"] = dict(self.per_robot)
        return out


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
        """How this run differs from the runs of the paper's figure 6 (`analysis.PAPER_*`);
        empty when it does not, and only then may its figures be set beside the paper's."""
        out = []
        if self.beacon_s is None:
            out.append("beacon unknown")
        elif not math.isclose(self.beacon_s, analysis.PAPER_BEACON_S):
            out.append(f"a {self.beacon_s:g} s beacon")
        low, high = analysis.PAPER_ROBOTS
        if not low <= self.robots <= high:
            out.append(_count(self.robots, "robot"))
        least, most = analysis.PAPER_SERVICES_PER_ROBOT
        if self.services_per_robot is None:
            out.append("services per robot unknown")
        elif not (least <= self.services_per_robot[0] and self.services_per_robot[1] <= most):
            out.append(f"{self._services()} per robot")
        # 5 minutes, give or take a beacon (a run's window starts with its captures).
        if self.duration_s < analysis.FIVE_MINUTES_S - analysis.PAPER_BEACON_S:
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
    for r in analysis.transmissions(recs):
        if r.msg_type == "Alive" and r.robot is not None:
            if r.robot in last:
                gaps.append(r.time - last[r.robot])
            last[r.robot] = r.time
    if not gaps:
        return None
    # sdfrd draws each gap from (1 - jitter) to 1 times its period: the median is the middle.
    return float(f"{statistics.median(gaps) / (1 - _BEACON_JITTER / 2):.2g}")


def write_report(
    run_dir: Path,
    *,
    records: Iterable[Record] | None,
    connectivity_samples: Sequence[ConnectivitySample | Mapping[str, Any]] | None = None,
    agreement_samples: Sequence[AgreementSample | Mapping[str, Any]] | None = None,
    meta: Mapping[str, Any] | None = None,
) -> dict[str, object]:
    """Write ``report.json`` and the plots into `run_dir`; return what ``report.json`` holds.

    `records=None` reads every ``*.pcap`` in `run_dir`.  `meta` (JSON-serialisable) is copied
    into the report; its ``start``/``end`` (UNIX seconds) or ``duration_s`` set the run's
    window.  Otherwise the window is the time the captures in `run_dir` ran (their ``.json``
    files), else the span of the records and samples.
    """
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    recs = analysis.read_run(run_dir) if records is None else sorted(records, key=_time)
    conn = [ConnectivitySample.coerce(s) for s in connectivity_samples or ()]
    agree = [AgreementSample.coerce(s) for s in agreement_samples or ()]
    meta = dict(meta or {})
    infos = analysis.capture_infos(run_dir)
    start, end = _window(recs, conn, agree, meta, infos)
    duration = end - start

    report: dict[str, Any] = {
        "schema": SCHEMA,
        "meta": meta,
        "window": {"start": start, "end": end, "duration_s": duration},
        "captures": _captures(recs, infos),
        "traffic": analysis.paper_measure(recs, duration=duration or None),
        "per_type": {k: v.to_json() for k, v in analysis.per_type(recs).items()},
        "rejects": analysis.rejects(recs),
        "updates": analysis.count_updates(recs),
        "arp": analysis.arp_counts(recs).to_json(),
        "plots": {},
    }
    robots = int(meta.get("robots") or len(report["traffic"]["robots"]))
    conditions = run_conditions(meta, recs, robots=robots, duration=duration)
    differences = conditions.paper_differences()
    report["conditions"] = {
        **conditions.to_json(),
        "paper_comparable": not differences,
        "paper_differences": differences,
    }
    if differences:  # the paper's figures go beside a run's only under the paper's conditions
        del report["traffic"]["paper_5_min_kB"]
    if conn:
        report["connectivity"] = _connectivity_summary(conn)
    if agree:
        report["agreement"] = _agreement_summary(agree)

    plots: dict[str, str] = report["plots"]
    # A run folder named after its scenario (the demo's) is named with its parent's.
    run = run_dir.name if run_dir.name != meta.get("scenario") else run_dir.absolute().parent.name
    timeline = draw.Timeline.of(
        meta, start, end, f"{run}/{run_dir.name}" if run != run_dir.name else run
    )
    plots["bytes_per_robot"] = draw.save(
        draw.bytes_per_robot(report["traffic"], conditions),
        run_dir / "bytes_per_robot.png",
        timeline,
    )
    plots["datagrams_per_type"] = draw.save(
        draw.datagrams_per_type(recs, start, end, timeline, beacon=conditions.beacon_s),
        run_dir / "datagrams_per_type.png",
        timeline,
    )
    if conn:
        plots["connectivity"] = draw.save(
            draw.connectivity(conn, start, end, timeline), run_dir / "connectivity.png", timeline
        )
    if agree:
        plots["agreement"] = draw.save(
            draw.agreement(agree, start, timeline), run_dir / "agreement.png", timeline
        )

    text = json.dumps(report, indent=2, sort_keys=False, default=_json_default) + "\n"
    tmp = run_dir / (REPORT_JSON + ".tmp")
    tmp.write_text(text)
    tmp.replace(run_dir / REPORT_JSON)
    result: dict[str, Any] = json.loads(text)
    return result


# ---------------------------------------------------------------------------------------------
# Figures


def _time(rec: Record) -> float:
    return rec.time


def _window(
    recs: Sequence[Record],
    conn: Sequence[ConnectivitySample],
    agree: Sequence[AgreementSample],
    meta: Mapping[str, Any],
    infos: Mapping[str, CaptureInfo],
) -> tuple[float, float]:
    times = [r.time for r in recs] + [s.time for s in conn] + [s.time for s in agree]
    began = [i.started for i in infos.values() if i.started is not None]
    ended = [i.stopped for i in infos.values() if i.stopped is not None]
    start = float(meta["start"]) if "start" in meta else min(began or times, default=0.0)
    if "end" in meta:
        end = float(meta["end"])
    elif "duration_s" in meta:
        end = start + float(meta["duration_s"])
    else:
        end = max(ended or times, default=start)
    return start, max(start, end)


def _captures(recs: Sequence[Record], infos: Mapping[str, CaptureInfo]) -> dict[str, object]:
    owners = analysis.capture_owners(recs)
    out: dict[str, dict[str, Any]] = {}
    for r in recs:
        c = out.setdefault(r.capture, _capture_entry(owners.get(r.capture)))
        c["frames"] += 1
        if r.kind in ("sdfr", "arp"):
            c[r.kind] += 1
        if r.direction in ("tx", "rx"):
            c[r.direction] += 1
    for label, info in infos.items():
        c = out.setdefault(label, _capture_entry(owners.get(label)))
        c["netns"], c["iface"], c["role"] = info.netns, info.iface, info.role
        c["tcpdump"] = asdict(info.stats)
    for c in out.values():
        c.setdefault("role", "robot" if c["tx"] or c["rx"] else "unknown")
    return {k: out[k] for k in analysis.natural_order(list(out))}


def _capture_entry(robot: str | None) -> dict[str, object]:
    return {"robot": robot, "frames": 0, "sdfr": 0, "arp": 0, "tx": 0, "rx": 0}


def _connectivity_summary(conn: Sequence[ConnectivitySample]) -> dict[str, object]:
    linked = [s.linked_pairs for s in conn]
    return {
        "samples": [s.to_json() for s in conn],
        "linked_pairs": {"min": min(linked), "max": max(linked), "mean": _mean(linked)},
    }


def _agreement_summary(agree: Sequence[AgreementSample]) -> dict[str, object]:
    values = [s.agreement for s in agree]
    return {
        "samples": [s.to_json() for s in agree],
        "mean": _mean(values),
        "min": min(values),
        "share_full": sum(v >= 1.0 for v in values) / len(values),
        "share_at_target": sum(v >= AGREEMENT_TARGET for v in values) / len(values),
        "target": AGREEMENT_TARGET,
    }


def _mean(values: Sequence[float]) -> float:
    return sum(values) / len(values) if values else math.nan


def _json_default(obj: object) -> Any:
    if hasattr(obj, "to_json"):
        return obj.to_json()
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, set | frozenset | tuple):
        return sorted(obj, key=str)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")
