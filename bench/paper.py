"""The paper's evaluation (its section 6, figures 4-6) in netlab, under the paper's load.

`make bench-paper` runs, at the product's defaults (10 s beacon), each in a lab of its own
and one after the other (so that no run takes CPU from another):

* the **static** scenario: 2, 4 and 6 robots standing in one hall, all in range, each with
  100 simulated services of which 30 %, 50 % or 70 % are publishers (nine runs);
* the **dynamic** scenario: 6 robots, 70 % publishers, walking on random waypoints in the
  paper's 200 m² hall (20 m x 10 m), over links that lose more the farther apart the robots
  are (clean up to 4 m, 40 % at 12 m, none beyond);

each for 5 minutes of load (`--minutes`; `--quick`: 30 s).  On every robot the load of
`bench.paper_load` runs (publishers publishing, unpublishing and publishing again as that
module's notes read the paper; consumers asking for the neighbour list as fast as they can).

Measured, per run: publish / unpublish / neighbour-list latency (p50, p99: the paper's
figure 4); CPU (% of one core) and PSS (MiB) of each daemon's whole process tree, sampled
every 2 s (figure 5); TX and RX bytes per robot over the 5 minutes of load from each
robot's capture, as UDP payload and as whole frames (figure 6); and how long each change took
to be seen on the other robots.  Then `bench.side_by_side` (python-zeroconf and Zenoh beside
SDfR on one lab) and the bytes per robot at 2, 6 and 20 robots (`--scale`), unless skipped.

Everything goes into one run folder (runs/bench-paper-<time>/): each run's pcaps and
daemon logs, `figures.json` (the data of every figure, the paper's numbers beside ours),
fig4-latency.png, fig5-cpu-memory.png, fig6-traffic.png, `tables.md` (the docs' tables; again
from a result: `python -m bench.paper_figures RESULT`) and `bench-paper.json`, the whole
result (also on stdout), with the machine's load average before and after each run.  Needs
root.  Exit status 1 when a run failed, 2 when the bench could not run.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from bench import compile_sdfr, err, paper_figures, paper_lab
from bench.paper_lab import (
    ROOT,
    SAMPLE_EVERY_S,
    SDFR_PORT,
    Sampler,
    captured,
    conditions,
    keep_logs,
)
from bench.paper_measure import (
    FIVE_MINUTES_S,
    PAPER,
    per_5_min,
    percentiles,
    propagation,
    read_events,
    spread,
    udp_traffic,
)
from netlab import naming
from netlab.lab import Lab
from netlab.mobility import HALL, RandomWaypoint
from netlab.ranges import LossyDisc, Pos

#: The dynamic scenario's links: clean up to 4 m, then losing more, up to 40 % at 12 m.
DYNAMIC_RANGE = LossyDisc(radius=12.0, clean=4.0, edge_loss=40.0)
#: Where static robots stand: a row 1 m apart, all in range of each other.
_STATIC_SPACING = 1.0


@dataclass(frozen=True, slots=True)
class Config:
    """One run of the paper's evaluation."""

    robots: int
    publishers_percent: int
    dynamic: bool = False
    consumers: bool = True

    @property
    def name(self) -> str:
        kind = "dynamic" if self.dynamic else "static"
        tail = "" if self.consumers else "-noconsumers"
        return f"{kind}-{self.robots}-{self.publishers_percent}{tail}"

    @property
    def publishers(self) -> int:
        return self.publishers_percent

    @property
    def consumer_threads(self) -> int:
        return 100 - self.publishers_percent if self.consumers else 0


#: The paper's grid: static 2, 4 and 6 robots x 30, 50 and 70 % publishers; dynamic 6 x 70.
GRID = [Config(n, p) for n in (2, 4, 6) for p in (30, 50, 70)] + [Config(6, 70, dynamic=True)]


def positions(cfg: Config, names: Sequence[str], seed: int) -> tuple[dict[str, Pos], Any]:
    if not cfg.dynamic:
        return {n: (2.0 + i * _STATIC_SPACING, 5.0) for i, n in enumerate(names)}, None
    model = RandomWaypoint(names, area=HALL, seed=seed)
    return model.positions_at(0.0), model


def wait_lists(lab: Lab, names: Sequence[str], timeout: float) -> float | None:
    """Seconds until every robot lists as reachable exactly the robots it hears (all the
    others, in a static fleet); None: not within `timeout`."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        ok = True
        for name in names:
            try:
                listed = {n["robot_id"] for n in lab.client(name).neighbors() if n["reachable"]}
            except Exception:
                ok = False
                break
            if listed != lab.neighbours(name):
                ok = False
                break
        if ok:
            return time.monotonic() - t0
        time.sleep(0.1)
    return None


def load_argv(cfg: Config, robot: str, duration: float, start_at: float, events: Path) -> list[str]:
    # Without consumers (the growth runs, up to 20 robots) no watcher either: reading a
    # 20-robot list 20 times a second on each robot would be a load of its own.
    watch = "0.05" if cfg.consumers else "0"
    return [
        sys.executable,
        "-m",
        "bench.paper_load",
        "--robot",
        robot,
        "--publishers",
        str(cfg.publishers),
        "--consumers",
        str(cfg.consumer_threads),
        "--duration",
        str(duration),
        "--start-at",
        repr(start_at),
        "--events",
        str(events),
        "--watch-interval",
        watch,
    ]


def run_config(cfg: Config, duration: float, folder: Path, seed: int = 1) -> dict[str, Any]:
    """One run: a lab of `cfg.robots` robots under the paper's load for `duration` s."""
    folder.mkdir(parents=True, exist_ok=True)
    names = [f"r{i}" for i in range(1, cfg.robots + 1)]
    where, model = positions(cfg, names, seed)
    before = conditions()
    lab_name = naming.unique_lab_name("p")
    err(f"bench-paper: {cfg.name}: lab {lab_name}, {duration:g} s of load")
    result: dict[str, Any] = {"config": cfg.name, "robots": cfg.robots, "conditions_before": before}
    with Lab(lab_name, seed=seed, range_model=DYNAMIC_RANGE if model else None) as lab:
        lab.add_robots(names, where)
        with captured(lab, folder, f"udp port {SDFR_PORT}") as caps:
            lab.start_all()  # the product's defaults: 10 s beacon
            up = wait_lists(lab, names, 60.0)
            result["startup_lists_match_medium_s"] = None if up is None else round(up, 2)
            start_at = time.time() + 1.0
            procs = []
            for name in names:
                out = open(folder / f"load-{name}.json", "w")  # noqa: SIM115 (closed below)
                argv = load_argv(cfg, name, duration, start_at, folder / f"events-{name}.jsonl")
                procs.append((name, out, lab.popen(name, argv, stdout=out, cwd=str(ROOT))))
            roots = {n: pid for n in names if (pid := lab.daemon_pid(n)) is not None}
            sampler = Sampler(roots)
            time.sleep(max(0.0, start_at - time.time()))
            sampler.start()
            timeline: list[tuple[float, Any]] = []
            walker = None
            if model is not None:

                def walk() -> None:
                    timeline.extend(
                        (start_at + t, links)
                        for t, links in lab.run_mobility(model, duration, step=0.5)
                    )

                walker = threading.Thread(target=walk, daemon=True)
                walker.start()
            for _, out, proc in procs:
                try:
                    proc.wait(timeout=duration + 120)
                finally:
                    out.close()
            sampler.stop()
            if walker is not None:
                walker.join(timeout=30)
            time.sleep(1.0)  # the last datagrams into the pcaps
            macs = {name: lab.robot(name).mac for name in names}
        keep_logs(lab, folder)
    end_at = start_at + duration
    loads = {}
    for name in names:
        text = (folder / f"load-{name}.json").read_text()
        loads[name] = json.loads(text) if text.strip() else {"error": "no output"}
    result["conditions_after"] = conditions()
    result["load"] = {
        "publishers": cfg.publishers,
        "consumers": cfg.consumer_threads,
        "duration_s": duration,
        "window": [start_at, end_at],
    }
    result["latency"] = latency(folder, names, loads)
    result["resources"] = resources(sampler.result())
    result["traffic"] = traffic(folder, names, macs, (start_at, end_at))
    linked = links_at(timeline) if model is not None else None
    result["seen_by_peers"] = (
        propagation(
            read_events(folder / f"events-{n}.jsonl" for n in names),
            names,
            until=end_at,
            linked=linked,
        )
        if cfg.consumers
        else {"skipped": "no watcher in a run without consumers (nothing is timed)"}
    )
    result["problems"] = [
        f"{n}: load generator: {v.get('error') or str(v.get('errors')) + ' failed requests'}"
        for n, v in loads.items()
        if v.get("error") or v.get("errors")
    ]
    if result["startup_lists_match_medium_s"] is None and not cfg.dynamic:  # (lossy links may lag)
        result["problems"].append("start-up: the lists did not match the medium within 60 s")
    del caps
    return result


def links_at(timeline: list[tuple[float, Any]]) -> Callable[[str, str, float], bool]:
    """Whether b heard a at time t, by the mobility steps (each holds until the next)."""
    times = [t for t, _ in timeline]

    def linked(a: str, b: str, t: float) -> bool:
        import bisect

        i = bisect.bisect_right(times, t) - 1
        if i < 0:
            return False
        # Heard all along the bound: at t and at the step after.
        j = min(i + 1, len(timeline) - 1)
        return (a, b) in timeline[i][1] and (a, b) in timeline[j][1]

    return linked


def latency(folder: Path, names: Sequence[str], loads: dict[str, Any]) -> dict[str, Any]:
    """Publish and unpublish latency over every robot (from each request's own note);
    neighbour-list latency per robot (each load generator's summary) and their spread."""
    events = read_events(folder / f"events-{n}.jsonl" for n in names)
    out: dict[str, Any] = {}
    for op in ("publish", "unpublish"):
        out[op] = percentiles(float(e["ms"]) for e in events if e["op"] == op)
    per_robot = {n: loads[n].get("neighbors", {}) for n in names}
    out["neighbors"] = {
        "per_robot": per_robot,
        "p50_ms": spread(v.get("p50_ms", float("nan")) for v in per_robot.values()),
        "p99_ms": spread(v.get("p99_ms", float("nan")) for v in per_robot.values()),
        "requests": sum(int(v.get("count", 0)) for v in per_robot.values()),
    }
    return out


def resources(per_robot: dict[str, Any]) -> dict[str, Any]:
    return {
        "per_robot": per_robot,
        "cpu_percent": spread(v.get("cpu_percent", float("nan")) for v in per_robot.values()),
        "pss_mib": spread(v.get("pss_mib_max", float("nan")) for v in per_robot.values()),
        "discovery_cpu_percent": spread(
            v["layers"].get("discovery", {}).get("cpu_percent", float("nan"))
            for v in per_robot.values()
        ),
        "api_cpu_percent": spread(
            v["layers"].get("api", {}).get("cpu_percent", float("nan")) for v in per_robot.values()
        ),
        "definition": (
            "the daemon's whole process tree (supervisor, API and discovery layers): CPU as % "
            f"of one core over the load, PSS sampled every {SAMPLE_EVERY_S:g} s (max over the "
            "run); per layer too"
        ),
    }


def traffic(
    folder: Path, names: Sequence[str], macs: dict[str, str], window: tuple[float, float]
) -> dict[str, Any]:
    """TX/RX per robot over the window, scaled to 5 minutes, with the datagram types."""
    seconds = window[1] - window[0]
    robots: dict[str, Any] = {}
    for name in names:
        t = udp_traffic(folder / f"{name}.pcap", macs[name], [SDFR_PORT], window)[SDFR_PORT]
        robots[name] = {
            "tx": t.tx.to_json(),
            "rx": t.rx.to_json(),
            "per_5_min_kB": {
                f"{d}_{s}": round(per_5_min(n, seconds) / 1000, 2)
                for d, flow in (("tx", t.tx), ("rx", t.rx))
                for s, n in (("payload", flow.payload_bytes), ("frame", flow.frame_bytes))
            },
        }
    out: dict[str, Any] = {
        "window_s": round(seconds, 1),
        "per_robot": robots,
        "per_5_min_kB": {
            key: spread(r["per_5_min_kB"][key] for r in robots.values())
            for key in ("tx_payload", "tx_frame", "rx_payload", "rx_frame")
        },
        "paper_5_min_kB": {"tx": list(PAPER["tx_kB_5min"]), "rx": list(PAPER["rx_kB_5min"])},  # type: ignore[call-overload]
        "by_type_tx_kB_per_robot_5_min": by_type(folder, names, window),
        "definition": (
            "TX: SDfR datagrams (UDP port 1900) a robot's capture saw it send; RX: those that "
            "reached its interface. payload = UDP payload; frame = whole Ethernet frame "
            "(+42 bytes). Counted over the load's window and scaled to 5 min. 1 kB = 1000 B."
        ),
    }
    return out


def by_type(folder: Path, names: Sequence[str], window: tuple[float, float]) -> dict[str, float]:
    """Sent bytes per message type, per robot, over 5 minutes (the SDfR dissector)."""
    from netlab import analysis, pcap

    recs = [
        r
        for r in pcap.read_run([folder / f"{n}.pcap" for n in names])
        if window[0] <= r.time <= window[1]
    ]
    seconds = window[1] - window[0]
    return {
        kind: round(per_5_min(t.payload_bytes, seconds) / len(names) / 1000, 2)
        for kind, t in analysis.per_type(recs).items()
    }


def summary_line(r: dict[str, Any]) -> str:
    t = r["traffic"]["per_5_min_kB"]
    lat = r["latency"]
    res = r["resources"]
    seen = r["seen_by_peers"].get("within_bound", "-")
    return (
        f"{r['config']:>22}  TX {t['tx_payload'].get('mean', 0):6.1f} kB  "
        f"RX {t['rx_payload'].get('mean', 0):6.1f} kB  "
        f"pub p50 {lat['publish'].get('p50_ms', 0):6.1f} ms  "
        f"unpub p50 {lat['unpublish'].get('p50_ms', 0):6.1f} ms  "
        f"nbrs p50 {lat['neighbors']['p50_ms'].get('mean', 0):6.1f} ms  "
        f"CPU {res['cpu_percent'].get('mean', 0):5.1f} %  PSS {res['pss_mib'].get('mean', 0):5.1f}"
        f" MiB  seen<=500ms {seen}"
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--quick", action="store_true", help="30 s of load per run, not 5 minutes")
    p.add_argument(
        "--smoke",
        action="store_true",
        help="CI's run: every part for seconds (static-2-30, dynamic-6-70, the side-by-side "
        "at a 1 s beacon, 2 robots for the growth), so the bench cannot rot; numbers mean "
        "nothing",
    )
    p.add_argument("--minutes", type=float, help="load per run (default 5; --quick 0.5)")
    p.add_argument(
        "--only",
        nargs="+",
        metavar="RUN",
        help="only these runs of the grid (e.g. static-2-30 dynamic-6-70); 'none' for none",
    )
    p.add_argument(
        "--no-side-by-side",
        action="store_true",
        help="skip the side-by-side (python-zeroconf, Zenoh)",
    )
    p.add_argument(
        "--scale",
        type=int,
        nargs="*",
        default=None,
        help="fleet sizes for the bytes-per-robot growth (default 2 6 20; --scale alone: skip)",
    )
    paper_lab.run_folder_options(p)
    args = p.parse_args(argv)
    if not paper_lab.has_root("bench-paper"):
        return 2
    if args.smoke:
        args.only = args.only or ["static-2-30", "dynamic-6-70"]
        args.scale = [2] if args.scale is None else args.scale
    default_minutes = 0.25 if args.smoke else 0.5 if args.quick else 5.0
    minutes = args.minutes if args.minutes is not None else default_minutes
    duration = minutes * 60.0
    grid = GRID
    if args.only is not None:
        wanted = set(args.only) - {"none"}
        unknown = wanted - {c.name for c in GRID}
        if unknown:
            err(f"bench-paper: no run named {', '.join(sorted(unknown))} in the grid")
            return 2
        grid = [c for c in GRID if c.name in wanted]
    scale = [2, 6, 20] if args.scale is None else args.scale
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    folder = Path(args.runs).absolute() / f"bench-paper-{stamp}"
    folder.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    result: dict[str, Any] = {
        "bench": "paper",
        "machine": {
            "nproc": len(os.sched_getaffinity(0)),
            "kernel": platform.release(),
            "python": platform.python_version(),
        },
        "bytecode": compile_sdfr(),
        "conditions_before": conditions(),
        "minutes_per_run": minutes,
        "mode": "smoke" if args.smoke else "quick" if args.quick else "full",
        "beacon_interval_s": 10.0,
        "load": load_reading(),
        "paper": {k: list(v) if isinstance(v, tuple) else v for k, v in PAPER.items()},
        "run_folder": str(folder),
        "runs": [],
        "problems": [],
    }
    for cfg in grid:
        try:
            r = run_config(cfg, duration, folder / cfg.name, seed=args.seed)
        except Exception as exc:
            result["problems"].append(f"{cfg.name}: {type(exc).__name__}: {exc}")
            err(f"bench-paper: {cfg.name} failed: {type(exc).__name__}: {exc}")
            continue
        result["runs"].append(r)
        result["problems"] += [f"{cfg.name}: {p}" for p in r["problems"]]
        err(summary_line(r))
    if not args.no_side_by_side:
        from bench import side_by_side

        try:
            timing = (
                side_by_side.SMOKE
                if args.smoke
                else side_by_side.QUICK
                if args.quick
                else side_by_side.FULL
            )
            result["side_by_side"] = side_by_side.run(
                folder / "side-by-side", timing, seed=args.seed
            )
            result["problems"] += result["side_by_side"].get("problems", [])
        except Exception as exc:
            result["problems"].append(f"side-by-side: {type(exc).__name__}: {exc}")
            err(f"bench-paper: side-by-side failed: {type(exc).__name__}: {exc}")
    result["scale"] = []
    for n in scale:
        cfg = Config(n, 70, consumers=False)
        try:
            r = run_config(cfg, duration, folder / cfg.name, seed=args.seed)
        except Exception as exc:
            result["problems"].append(f"{cfg.name}: {type(exc).__name__}: {exc}")
            continue
        result["scale"].append(r)
        result["problems"] += [f"{cfg.name}: {p}" for p in r["problems"]]
        err(summary_line(r))
    result["conditions_after"] = conditions()
    result["wall_s"] = round(time.monotonic() - t0, 1)
    figures = paper_figures.figures(result)
    result["figures"] = paper_figures.write(figures, folder)
    (folder / "tables.md").write_text(paper_figures.markdown(result))
    result["figures"]["tables"] = str(folder / "tables.md")
    text = json.dumps(result, indent=2)
    (folder / "bench-paper.json").write_text(text + "\n")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    print(text, flush=True)
    err(f"bench-paper: {folder} ({result['wall_s']:.0f} s)")
    if result["problems"]:
        err("bench-paper: PROBLEMS\n  " + "\n  ".join(result["problems"]))
        return 1
    return 0


def load_reading() -> dict[str, Any]:
    """The paper's load as this bench reads it (see bench.paper_load)."""
    return {
        "services_per_robot": 100,
        "publish": "each publisher publishes 10 s after the load starts and 10 s after each "
        "time it was unpublished; every publish is a new registration (fresh id), the same "
        "service otherwise",
        "unpublish": "per robot, after a random delay uniform in 0-5 s, one published "
        "service chosen uniformly is unpublished; again and again (0.4 unpublishes and, "
        "in steady state, 0.4 publishes a second per robot)",
        "consumers": "each a thread asking GET /neighbors again the moment it has the answer",
        "watcher": "one more thread per robot reads GET /neighbors every 50 ms to time when "
        "changes are seen (not one of the paper's consumers)",
        "five_minutes_s": FIVE_MINUTES_S,
    }


if __name__ == "__main__":
    raise SystemExit(main())
