"""A run's report: ``report.json`` (figures) and PNG plots, written into the run's folder.

`write_report(run_dir, records=...)` takes the records of the run's captures
(`netlab.pcap.read_run`) and, when the scenario sampled them, connectivity and
neighbour-table agreement over time (`netlab.samples`).  Its ``traffic`` is the paper's
measure (`netlab.paper`).  All times are UNIX seconds (``time.time()``), the clock of the
pcaps; plots show seconds since the start of the run.

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
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

from netlab import analysis
from netlab import plots as draw
from netlab.capture import CaptureInfo
from netlab.paper import RunConditions, paper_measure, run_conditions
from netlab.pcap import Record, capture_infos, read_run
from netlab.samples import AgreementSample, ConnectivitySample

__all__ = ["AGREEMENT_TARGET", "REPORT_JSON", "write_report"]

REPORT_JSON = "report.json"
SCHEMA = "netlab-report/1"
#: Share of the samples in which neighbour lists must agree with the truth, the bar the report
#: counts samples against (``share_at_target``).
AGREEMENT_TARGET = 0.95


def write_report(
    run_dir: Path,
    *,
    records: Iterable[Record] | None,
    connectivity_samples: Sequence[ConnectivitySample | Mapping[str, Any]] | None = None,
    agreement_samples: Sequence[AgreementSample | Mapping[str, Any]] | None = None,
    meta: Mapping[str, Any] | None = None,
    plots: bool = True,
) -> dict[str, object]:
    """Write ``report.json`` and the plots into `run_dir`; return what ``report.json`` holds.
    Without `plots` its ``plots`` are empty (`netlab report RUN` draws them later).

    `records=None` reads every ``*.pcap`` in `run_dir`.  `meta` (JSON-serialisable) is copied
    into the report; its ``start``/``end`` (UNIX seconds) or ``duration_s`` set the run's
    window.  Otherwise the window is the time the captures in `run_dir` ran (their ``.json``
    files), else the span of the records and samples.
    """
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    recs = read_run(run_dir) if records is None else sorted(records, key=_time)
    conn = [ConnectivitySample.coerce(s) for s in connectivity_samples or ()]
    agree = [AgreementSample.coerce(s) for s in agreement_samples or ()]
    meta = dict(meta or {})
    infos = capture_infos(run_dir)
    start, end = _window(recs, conn, agree, meta, infos)
    duration = end - start

    report: dict[str, Any] = {
        "schema": SCHEMA,
        "meta": meta,
        "window": {"start": start, "end": end, "duration_s": duration},
        "captures": _captures(recs, infos),
        "traffic": paper_measure(recs, duration=duration or None),
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
    air = analysis.air_use(recs, _radio_owners(recs, infos, meta))
    if air:
        report["air"] = air
    if conn:
        report["connectivity"] = _connectivity_summary(conn)
    if agree:
        report["agreement"] = _agreement_summary(agree)

    if plots:
        _draw(run_dir, report, recs, conn, agree, meta, conditions, start, end)

    text = json.dumps(report, indent=2, sort_keys=False, default=_json_default) + "\n"
    tmp = run_dir / (REPORT_JSON + ".tmp")
    tmp.write_text(text)
    tmp.replace(run_dir / REPORT_JSON)
    result: dict[str, Any] = json.loads(text)
    return result


# ---------------------------------------------------------------------------------------------
# The report's parts: its window, its captures, the summaries of the samples


def _draw(
    run_dir: Path,
    report: dict[str, Any],
    recs: Sequence[Record],
    conn: Sequence[ConnectivitySample],
    agree: Sequence[AgreementSample],
    meta: Mapping[str, Any],
    conditions: RunConditions,
    start: float,
    end: float,
) -> None:
    """The run's PNGs, each named in ``report["plots"]``."""
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


def _radio_owners(
    recs: Sequence[Record], infos: Mapping[str, CaptureInfo], meta: Mapping[str, Any]
) -> dict[str, str]:
    """A robot's interface MAC -> the robot: who sent what on the air.  From the run's
    meta (the lab's radios), else from the robots' own captures."""
    owners = analysis.capture_owners(recs)
    named = {mac: robot for robot, mac in (meta.get("radios") or {}).items()}
    return named | {
        info.mac: owners.get(label, label)
        for label, info in infos.items()
        if info.mac and info.role != "medium"
    }


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
