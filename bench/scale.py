"""How sdfrd scales: 10, 50 and 100 robots with real daemons in one netlab lab on this
machine, at the product's 10 s beacon (make bench-scale).

Each size runs the bundled scale-100 scenario with its robot count set (every robot in range
of every other, each publishing one service): start-up, convergence (every robot lists all
the others with their services), then a "stay" of two minutes (--quick: 30 s) in which every
sample of every robot's list must agree with the medium (no flap). For each size:

- set-up time (the start step: every sdfrd healthy) and convergence time (publish -> all
  list all);
- CPU and memory per daemon over the stay (the scenario's resources check: % of one core,
  PSS and RSS of each daemon's process tree);
- bytes on the air per robot per second over the stay, from the medium's capture (each
  datagram once, as it went out): TX by sender, RX by who it reached (a multicast reaches
  every other robot, a unicast its addressee), and the fleet's datagrams per second by type.

Then how each figure grows with n: the exponent b of a fit figure ~ n^b between the sizes
(1: linear, 2: quadratic). Per robot, RX grows at least linearly (every robot hears every
beacon); what must not grow with n is anything per robot per peer.

JSON on stdout and in --out (runs/bench-scale.json), with the load average before and after
each size; a plot in --plot (docs/scale-growth.png); a table on stderr. Needs root.

With --hosts N (make bench-scale-hosts): the lab spread over N hosts simulated on this machine
(`netlab.hostsim`: namespaces with their own sshd, driven over ssh like machines), running
--scenario (scale-300: each robot hears ~16, not all); per size, also what the lab's VXLAN
carried on the underlay over the stay (each host's counters, read with the resources check's
readings) beside the frames the medium carried (the span's overhead).
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import math
import os
import platform
import statistics
import sys
import time
from collections import Counter, defaultdict
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

from bench import compile_sdfr, err
from netlab import pcap, scenario
from netlab.vxlan import OVERHEAD

ROOT = Path(__file__).resolve().parent.parent


def loadavg() -> list[float]:
    return [float(x) for x in Path("/proc/loadavg").read_text().split()[:3]]


def step_window(report: dict[str, Any], label: str) -> tuple[float, float]:
    for step in report["meta"]["steps"]:
        if step["label"] == label and step["start"] is not None and step["end"] is not None:
            return float(step["start"]), float(step["end"])
    raise SystemExit(f"bench: the run's report has no step {label!r}")


def air(
    run_dir: Path, start: float, end: float, n: int, reach: dict[str, set[str]] | None = None
) -> dict[str, Any]:
    """Bytes and datagrams on the air over [start, end], from the medium's capture; a
    multicast reaches every other robot, or those in `reach` of its sender (robots that do
    not move: the scenario's positions and radius)."""
    recs = [
        r
        for r in pcap.read_run([run_dir / "medium.pcap"])
        if r.kind == pcap.SDFR and start <= r.time <= end
    ]
    seconds = end - start
    owner = {r.src: r.robot for r in recs if r.robot is not None}
    tx: dict[str, int] = defaultdict(int)
    rx: dict[str, int] = defaultdict(int)
    robots = sorted(set(owner.values()))
    kinds: Counter[str] = Counter()
    kind_bytes: Counter[str] = Counter()
    for r in recs:
        sender = r.robot or owner.get(r.src, "?")
        tx[sender] += r.payload_len
        kinds[r.type_key] += 1
        kind_bytes[r.type_key] += r.payload_len
        if r.multicast:
            for robot in robots if reach is None else reach.get(sender, ()):
                if robot != sender:
                    rx[robot] += r.payload_len
        elif r.dst in owner:
            rx[owner[r.dst]] += r.payload_len
    per_s = {robot: tx[robot] / seconds for robot in robots}
    rx_s = {robot: rx[robot] / seconds for robot in robots}
    return {
        "window_s": round(seconds, 1),
        "robots_heard": len(robots),
        "tx_bytes_per_robot_per_s": spread(list(per_s.values())),
        "rx_bytes_per_robot_per_s": spread(list(rx_s.values())),
        "fleet_bytes_per_s": round(sum(tx.values()) / seconds, 1),
        "fleet_datagrams_per_s_by_type": {
            k: round(v / seconds, 2) for k, v in sorted(kinds.items())
        },
        "datagrams_per_robot_per_s_by_type": {
            k: round(v / seconds / n, 3) for k, v in sorted(kinds.items())
        },
        "bytes_per_robot_per_s_by_type": {
            k: round(v / seconds / n, 1) for k, v in sorted(kind_bytes.items())
        },
    }


def spread(values: list[float]) -> dict[str, float]:
    if not values:
        return {"mean": 0.0, "min": 0.0, "max": 0.0}
    return {
        "mean": round(statistics.fmean(values), 1),
        "min": round(min(values), 1),
        "max": round(max(values), 1),
    }


def run_size(
    n: int, base: scenario.Scenario, args: argparse.Namespace, backend: Any = None
) -> dict[str, Any]:
    sc = replace(base, robots=n, name=f"{base.name}-{n}" if n != base.robots else base.name)
    before = loadavg()
    t0 = time.monotonic()
    res = scenario.run(sc, runs=args.runs, quick=args.quick, say=lambda s: err(f"  [{n}] {s}"),
                       backend=backend)  # fmt: skip
    out: dict[str, Any] = {
        "robots": n,
        "status": res.status,
        "run_dir": str(res.run_dir),
        "run_s": round(time.monotonic() - t0, 1),
        "loadavg_before": before,
        "loadavg_after": loadavg(),
        "checks": [
            {"description": c.description, "result": c.result, "detail": c.detail}
            for c in res.checks
        ],
    }
    if res.error:
        out["error"] = res.error
    if res.report is None or res.run_dir is None:
        return out
    start, end = step_window(res.report, "start-up")
    out["setup_s"] = round(end - start, 2)
    for c in res.checks:
        if c.kind in ("lists", "medium") and c.took is not None and "converge" in c.description:
            out["converge_s"] = round(c.took, 2)
        if c.kind == "agreement":
            out["agreement"] = c.data or c.detail
        if c.kind == "resources" and c.data:
            d = c.data
            out["cpu_percent_per_daemon"] = {
                k: round(v, 4) for k, v in d["cpu_percent"].items() if k in ("mean", "max")
            }
            out["pss_mib_per_daemon"] = {
                k: round(v, 2) for k, v in d["pss_mib"].items() if k in ("mean", "max")
            }
            out["rss_mib_per_daemon"] = {k: round(v, 2) for k, v in d["rss_mib"].items()}
    stay = step_window(res.report, "stay")
    out["air"] = air(res.run_dir, stay[0], stay[1], n, in_reach(sc))
    span = res.report["meta"].get("span_readings")
    if span:
        out["hosts"] = {h: len(v["robots"]) for h, v in res.report["meta"]["hosts"].items()}
        out["span"] = span_cost(span, stay, res.run_dir)
    return out


def in_reach(sc: scenario.Scenario) -> dict[str, set[str]] | None:
    """Who hears whom, for a scenario whose robots stand still where it puts them (None when
    every robot is in range of every other: the plain count is right)."""
    from netlab.ranges import Topology, UnitDisc

    medium = Topology(UnitDisc(sc.radius))  # the scenario's medium, as the lab builds it
    pos = sc.initial_positions()
    for robot, at in pos.items():
        medium.add(robot, at)
    reach: dict[str, set[str]] = {robot: set() for robot in pos}
    for sender, receiver in medium.links():
        reach[sender].add(receiver)
    return None if all(len(v) == len(pos) - 1 for v in reach.values()) else reach


def span_cost(readings: list[dict[str, Any]], stay: tuple[float, float], run_dir: Path) -> Any:
    """What the VXLAN carried on the underlay over the stay (the readings at its ends), beside
    the frames the medium carried then (each once, from the merged medium capture)."""
    first, last = readings[0], readings[-1]
    seconds = last["time"] - first["time"]
    tx = sum(last["hosts"][h]["tx_bytes"] - first["hosts"][h]["tx_bytes"] for h in last["hosts"])
    pkts = sum(
        last["hosts"][h]["tx_packets"] - first["hosts"][h]["tx_packets"] for h in last["hosts"]
    )
    frames = [r for r in pcap.read_run([run_dir / "medium.pcap"]) if stay[0] <= r.time <= stay[1]]
    medium = sum(r.frame_len for r in frames) / (stay[1] - stay[0])
    # The VXLAN device counts the frames it carried; each went out with VXLAN's 50 bytes
    # (outer IPv4, UDP, VXLAN, Ethernet) once per other host it was sent to.
    underlay = (tx + pkts * OVERHEAD) / seconds
    return {
        "window_s": round(seconds, 1),
        "vxlan_frame_bytes_per_s": round(tx / seconds, 1),
        "vxlan_frames_per_s": round(pkts / seconds, 1),
        "underlay_bytes_per_s": round(underlay, 1),
        "medium_frame_bytes_per_s": round(medium, 1),
        "underlay_per_medium_byte": round(underlay / medium, 2) if medium else None,
    }


@contextlib.contextmanager
def simulated_hosts(n: int, runs: Path, robots: int) -> Iterator[Any]:
    """N hosts simulated on this machine, and the scenario backend for labs across them (of
    `robots` at most: the machine's ARP table is raised for them)."""
    from netlab import hostsim, naming
    from netlab.hosts import Ssh
    from netlab.spanlab import span_backend

    missing = hostsim.needs()
    if missing:
        raise SystemExit(f"bench: simulated hosts need {missing} (scripts/bootstrap.sh)")
    folder = runs / "bench-hosts"
    folder.mkdir(parents=True, exist_ok=True)
    with hostsim.SimHosts(naming.unique_lab_name("h"), n, folder, robots=robots) as sim:
        hosts = [(Ssh(h.alias, sim.ssh_config, sys.executable, control_dir=sim.control_dir),
                  h.address) for h in sim.hosts]  # fmt: skip
        yield span_backend(hosts, env={"PYTHONPATH": str(ROOT)})


def growth(sizes: list[dict[str, Any]], path: tuple[str, ...]) -> dict[str, Any]:
    """The exponent b of value ~ n^b between consecutive sizes that have the value."""
    points = []
    for s in sizes:
        v: Any = s
        for key in path:
            v = v.get(key) if isinstance(v, dict) else None
        if isinstance(v, int | float) and v > 0:
            points.append((s["robots"], float(v)))
    out: dict[str, Any] = {"values": {str(n): v for n, v in points}}
    out["exponent"] = {
        f"{a[0]}->{b[0]}": round(math.log(b[1] / a[1]) / math.log(b[0] / a[0]), 2)
        for a, b in itertools.pairwise(points)
    }
    return out


def label_axes(ax: Any, ylabel: str, title: str) -> None:
    """One of the growth plots' panels: robots across, `ylabel` up, its title and legend."""
    ax.set_xlabel("robots")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend(fontsize=8)


def plot(res: dict[str, Any], where: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        err("bench: no matplotlib, no plot (pip install 'sdfr-robots[netlab]')")
        return
    sizes = [s for s in res["sizes"] if "air" in s]
    if not sizes:
        return
    ns = [s["robots"] for s in sizes]
    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    tx = [s["air"]["tx_bytes_per_robot_per_s"]["mean"] for s in sizes]
    rx = [s["air"]["rx_bytes_per_robot_per_s"]["mean"] for s in sizes]
    ax = axes[0]
    ax.plot(ns, tx, "o-", label="TX per robot")
    ax.plot(ns, rx, "s-", label="RX per robot")
    ax.plot(ns, [tx[0] * n / ns[0] for n in ns], ":", color="grey", label="TX, linear in n")
    label_axes(ax, "UDP payload bytes/s per robot", "on the air (steady state)")
    ax = axes[1]
    kinds = sorted({k for s in sizes for k in s["air"]["datagrams_per_robot_per_s_by_type"]})
    for kind in kinds:
        ax.plot(
            ns,
            [s["air"]["datagrams_per_robot_per_s_by_type"].get(kind, 0.0) for s in sizes],
            "o-",
            label=kind,
        )
    label_axes(ax, "datagrams/s sent per robot", "what each robot sends, by type")
    ax = axes[2]
    cpu = [s.get("cpu_percent_per_daemon", {}).get("mean", 0.0) for s in sizes]
    ax.plot(ns, cpu, "o-", label="CPU per daemon (% of a core)")
    ax.plot(ns, [cpu[0] * n / ns[0] for n in ns], ":", color="grey", label="linear in n")
    label_axes(ax, "% of one core", "CPU per daemon over the stay")
    load = ", ".join(f"{s['robots']}: {s['loadavg_before'][0]:.1f}" for s in sizes)
    fig.suptitle(
        f"sdfrd at the 10 s beacon, all robots in range, one 2-core machine "
        f"(load average before each run: {load})",
        fontsize=9,
    )
    fig.tight_layout()
    where.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(where, dpi=110)
    plt.close(fig)


def table(res: dict[str, Any]) -> str:
    lines = [
        f"{'robots':>6} {'status':>7} {'setup s':>8} {'conv s':>7} {'CPU %':>7} {'PSS MiB':>8} "
        f"{'TX B/s':>8} {'RX B/s':>8}"
    ]
    for s in res["sizes"]:
        a = s.get("air", {})
        lines.append(
            f"{s['robots']:>6} {s['status']:>7} {s.get('setup_s', float('nan')):>8.1f} "
            f"{s.get('converge_s', float('nan')):>7.1f} "
            f"{s.get('cpu_percent_per_daemon', {}).get('mean', float('nan')):>7.3f} "
            f"{s.get('pss_mib_per_daemon', {}).get('mean', float('nan')):>8.1f} "
            f"{a.get('tx_bytes_per_robot_per_s', {}).get('mean', float('nan')):>8.0f} "
            f"{a.get('rx_bytes_per_robot_per_s', {}).get('mean', float('nan')):>8.0f}"
        )
    for s in res["sizes"]:
        if "span" in s:
            sp = s["span"]
            lines.append(
                f"{s['robots']} robots on hosts {s['hosts']}: the VXLAN put "
                f"{sp['underlay_bytes_per_s']:.0f} B/s on the underlay for "
                f"{sp['medium_frame_bytes_per_s']:.0f} B/s of frames on the medium "
                f"({sp['underlay_per_medium_byte']} underlay bytes per medium byte)"
            )
    for key, g in res["growth"].items():
        lines.append(f"growth of {key}: exponent {g['exponent']}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--robots", default="10,50,100", help="fleet sizes, comma-separated")
    p.add_argument("--quick", action="store_true", help="a 30 s stay instead of 2 minutes")
    p.add_argument("--runs", type=Path, default=ROOT / "runs", help="where run folders go")
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "bench-scale.json")
    p.add_argument("--plot", type=Path, default=ROOT / "docs" / "scale-growth.png")
    p.add_argument("--hosts", type=int, default=0, help="spread over N simulated hosts")
    p.add_argument("--scenario", default=None, help="default scale-100 (scale-300 with --hosts)")
    args = p.parse_args(argv)
    if os.geteuid() != 0:
        err("bench: needs root (robots are network namespaces)")
        return 2
    bytecode = compile_sdfr()
    base = scenario.load(
        scenario.find(args.scenario or ("scale-300" if args.hosts else "scale-100"))
    )
    sizes = []
    with contextlib.ExitStack() as stack:
        backend = None
        counts = [int(x) for x in args.robots.split(",")]
        if args.hosts:
            backend = stack.enter_context(simulated_hosts(args.hosts, args.runs, max(counts)))
        for n in counts:
            err(f"bench: {n} robots ...")
            sizes.append(run_size(n, base, args, backend))
    res: dict[str, Any] = {
        "bench": "scale",
        "scenario": base.name,
        "hosts": args.hosts or 1,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "bytecode": bytecode,
        "beacon_s": base.beacon,
        "stay": "30 s (--quick)" if args.quick else "2 min",
        "sizes": sizes,
    }
    res["growth"] = {
        "tx_bytes_per_robot_per_s": growth(sizes, ("air", "tx_bytes_per_robot_per_s", "mean")),
        "rx_bytes_per_robot_per_s": growth(sizes, ("air", "rx_bytes_per_robot_per_s", "mean")),
        "fleet_bytes_per_s": growth(sizes, ("air", "fleet_bytes_per_s")),
        "cpu_percent_per_daemon": growth(sizes, ("cpu_percent_per_daemon", "mean")),
        "pss_mib_per_daemon": growth(sizes, ("pss_mib_per_daemon", "mean")),
        "setup_s": growth(sizes, ("setup_s",)),
    }
    text = json.dumps(res, indent=2)
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text + "\n")
    plot(res, args.plot)
    err(table(res))
    return 0 if all(s["status"] == "passed" for s in sizes) else 1


if __name__ == "__main__":
    raise SystemExit(main())
