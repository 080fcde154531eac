"""SDfR's own traffic per robot (the paper's Figure 6) at the product's 10 s beacon.

The bundled static-2, static-4 and static-6 scenarios (2, 4 and 6 robots standing in one
hall, all in range, each publishing two services; the paper's evaluation) run with the beacon
set to 10 s and their "stay" step lasting --minutes (5, the paper's run length). Every robot's
interface is captured; the run's report counts, per robot, the SDfR datagrams it sent (TX) and
those that reached its interface (RX), as UDP payload bytes and as whole Ethernet frames
(`netlab.paper.paper_measure`). These are scaled to exactly 5 minutes of the daemons
running (1 kB = 1000 bytes). Not the paper's load (its robots published 30-70 services each
and changed them): the paper's figure 6 is not set beside these, and the JSON says how the
conditions differ (`paper_conditions`); `make bench-paper` measures under the paper's load.

The fleets run at the same time, each on its own lab (its own namespaces and medium bridge),
so the whole bench takes about --minutes plus a little. A lab's captures see only its own
medium: one fleet's bytes never include another's. Only the CPU is shared.

JSON on stdout and in --out (runs/bench-traffic.json); progress and a table on stderr. Exit
status 1 when a scenario run did not pass, 2 when it could not run. Needs root.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import threading
import time
from collections import Counter, defaultdict
from dataclasses import replace
from datetime import datetime
from pathlib import Path
from typing import Any

from netlab import analysis, cleanup, manifest, naming, paper, pcap, scenario
from netlab.errors import NetlabError

ROOT = Path(__file__).resolve().parent.parent
FIVE_MINUTES_S = 300.0
SIZES = ("payload", "frame")
_print_lock = threading.Lock()


def err(text: str) -> None:
    with _print_lock:
        print(text, file=sys.stderr, flush=True)


def prepare(n: int, beacon: float, minutes: float) -> scenario.Scenario:
    """static-<n> at this beacon, its one sleep step lasting `minutes` (never in beacons)."""
    try:
        sc = scenario.load(scenario.find(f"static-{n}"))
    except scenario.ScenarioError as exc:
        raise SystemExit(f"bench: {exc}") from None
    sleeps = [i for i, s in enumerate(sc.steps) if isinstance(s, scenario.Sleep)]
    if len(sleeps) != 1:
        raise SystemExit(f"bench: {sc.source}: expected one sleep step, found {len(sleeps)}")
    steps = list(sc.steps)
    step = steps[sleeps[0]]
    assert isinstance(step, scenario.Sleep)
    if scenario.Duration.of(step.duration).beacons:
        raise SystemExit(
            f"bench: {sc.source}: the sleep lasts {step.duration!r}, in beacons: it would scale "
            "with the beacon; expected seconds or minutes"
        )
    steps[sleeps[0]] = replace(step, duration=minutes * 60.0)
    return replace(sc, beacon=beacon, steps=tuple(steps))


def robot_records(res: scenario.RunResult) -> tuple[list[pcap.Record], float | None]:
    """The robots' captured records, and when the last robot capture stopped."""
    assert res.run_dir is not None
    infos = {
        label: info
        for label, info in pcap.capture_infos(res.run_dir).items()
        if info.role == "robot"
    }
    recs = pcap.read_run([res.run_dir / f"{label}.pcap" for label in infos])
    stops = [i.stopped for i in infos.values() if i.stopped is not None]
    return recs, max(stops, default=None)


def live_window(res: scenario.RunResult, recs: list[pcap.Record], stop: float | None) -> Any:
    """The seconds SDfR ran under capture: from the first datagram any robot sent (daemons
    start a few seconds apart; on a busy machine the start step takes longer than that) to the
    captures' stop; the report's whole-run window if that cannot be told."""
    assert res.report is not None
    sent = analysis.transmissions(recs)
    firsts: dict[str, float] = {}
    for r in sent:
        if r.robot is not None:
            firsts.setdefault(r.robot, r.time)
    if firsts and stop is not None:
        began = min(firsts.values())
        return {
            "seconds": round(stop - began, 3),
            "from": "the first SDfR datagram of the fleet to the captures' stop",
            "robots_first_datagram_spread_s": round(max(firsts.values()) - began, 3),
        }
    return {
        "seconds": float(res.report["window"]["duration_s"]),
        "from": "the whole run (lab up to lab down)",
    }


def spread(values: list[float], ndigits: int = 1) -> dict[str, float]:
    return {
        "min": round(min(values), ndigits),
        "max": round(max(values), ndigits),
        "mean": round(statistics.fmean(values), ndigits),
    }


def summarise(n: int, sc: scenario.Scenario, res: scenario.RunResult) -> dict[str, object]:
    assert res.report is not None
    traffic = res.report["traffic"]
    recs, stop = robot_records(res)
    window = live_window(res, recs, stop)
    scale = FIVE_MINUTES_S / window["seconds"]
    kinds: dict[str, Counter[str]] = defaultdict(Counter)
    for r in analysis.transmissions(recs):
        kinds[r.robot or "?"][r.type_key] += 1
    robots: dict[str, Any] = {}
    for robot, t in traffic["robots"].items():
        robots[robot] = {
            d: {
                "datagrams": t[d]["datagrams"],
                "payload_bytes": t[d]["payload_bytes"],
                "frame_bytes": t[d]["frame_bytes"],
                "per_5_min_kB": {s: round(t[d][f"{s}_bytes"] * scale / 1000, 2) for s in SIZES},
            }
            for d in ("tx", "rx")
        }
        robots[robot]["tx"]["datagrams_per_type"] = dict(sorted(kinds[robot].items()))
    per_5_min = {
        d: {s: spread([r[d]["per_5_min_kB"][s] for r in robots.values()]) for s in SIZES}
        for d in ("tx", "rx")
    }
    per_type = {
        kind: {
            **totals,
            "datagrams_per_robot_per_5_min": round(totals["datagrams"] * scale / n, 1),
        }
        for kind, totals in res.report.get("per_type", {}).items()
    }
    return {
        "robots": n,
        "scenario": sc.name,
        "status": res.status,
        "run_dir": str(res.run_dir),
        "run_s": round(res.duration, 1),
        "measured_window": window,
        "report_window_s": round(float(res.report["window"]["duration_s"]), 3),
        "scale_to_5_min": round(scale, 4),
        "per_robot": robots,
        "per_5_min_kB": per_5_min,
        "sent_per_type_fleet": per_type,
        "arp_frames": res.report.get("arp"),
        "problem": (
            None if len(robots) == n else f"the report has the traffic of {len(robots)} robots"
        ),
    }


def table(sizes: list[dict[str, Any]]) -> str:
    def rng(entry: dict[str, Any], d: str, s: str) -> str:
        v = entry["per_5_min_kB"][d][s]
        return f"{v['min']:.0f}-{v['max']:.0f}"

    lines = [
        "kB per robot over 5 min (1 kB = 1000 B; UDP payload, whole frames in brackets);",
        f"not the paper's load ({paper.PAPER_CONDITIONS}, and changes): not comparable",
        f"{'robots':>6}  {'TX kB':>17}  {'RX kB':>17}  status",
    ]
    for e in sizes:
        tx = f"{rng(e, 'tx', 'payload')} ({rng(e, 'tx', 'frame')})"
        rx = f"{rng(e, 'rx', 'payload')} ({rng(e, 'rx', 'frame')})"
        lines.append(f"{e['robots']:>6}  {tx:>17}  {rx:>17}  {e['status']}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--sizes", type=int, nargs="+", default=[2, 4, 6], help="fleet sizes")
    p.add_argument("--beacon", type=float, default=scenario.PRODUCT_BEACON, help="seconds")
    p.add_argument(
        "--minutes", type=float, default=5.0, help="how long each fleet stays (the paper: 5)"
    )
    p.add_argument("--runs", type=Path, default=ROOT / "runs", help="where run folders go")
    p.add_argument(
        "--out", type=Path, default=ROOT / "runs" / "bench-traffic.json", help="JSON file"
    )
    args = p.parse_args(argv)
    if os.geteuid() != 0:
        err("bench: needs root (it runs robots in network namespaces)")
        return 2
    if args.minutes <= 0 or args.beacon <= 0:
        err("bench: --minutes and --beacon must be positive")
        return 2
    sizes = list(dict.fromkeys(args.sizes))
    plans = {n: prepare(n, args.beacon, args.minutes) for n in sizes}
    suffix = naming.b36(os.getpid() % 36**4, 4)
    labs = {n: naming.check_lab_name(f"tx{n}{suffix}") for n in sizes}
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    folder = Path(args.runs).absolute() / f"bench-traffic-{stamp}"
    results: dict[int, scenario.RunResult] = {}
    crashes: dict[int, str] = {}

    def one(n: int) -> None:
        def say(text: str) -> None:
            err("\n".join(f"[{n} robots] {line}" for line in text.splitlines()))

        try:
            results[n] = scenario.run(
                plans[n], lab_name=labs[n], run_dir=folder / f"static-{n}", say=say
            )
        except Exception as exc:  # reported below; the run has taken its lab down
            crashes[n] = f"{type(exc).__name__}: {exc}"

    # No SIGTERM handler: pyroute2 stops the helpers it forks with SIGTERM, and a handler
    # inherited by them would run this program on in the child.
    err(
        f"bench: static-{', static-'.join(map(str, sizes))} at beacon {args.beacon:g} s, "
        f"{args.minutes:g} min each, at the same time (labs {', '.join(labs.values())}); "
        f"run folders in {folder}"
    )
    t0 = time.monotonic()
    threads = [threading.Thread(target=one, args=(n,), daemon=True) for n in sizes]
    try:
        for t in threads:
            t.start()
        for t in threads:
            while t.is_alive():
                t.join(0.5)
    except KeyboardInterrupt:
        err("bench: interrupted; taking the labs down")
        for lab in labs.values():
            try:
                cleanup.sweep(lab, manifest.load(lab))
            except NetlabError as exc:
                err(f"bench: {exc} (`netlab down {lab}` to retry)")
        return 130
    left = [thing for lab in labs.values() for thing in cleanup.leftovers(lab)]

    problems = [f"static-{n}: {crashes[n]}" for n in sorted(crashes)]
    for n in sizes:
        res = results.get(n)
        if res is None:
            continue
        if not res.ok:
            why = res.error or res.reason or "; ".join(c.description for c in res.failed)
            problems.append(f"static-{n}: {res.status}: {why} (run folder {res.run_dir})")
        elif res.report is None:
            problems.append(f"static-{n}: no report was written (run folder {res.run_dir})")
    if left:
        problems.append(f"left behind: {', '.join(left)}")
    fleets = [
        summarise(n, plans[n], results[n])
        for n in sizes
        if n in results and results[n].report is not None
    ]
    problems += [f"static-{e['robots']}: {e['problem']}" for e in fleets if e["problem"]]
    wall = time.monotonic() - t0  # the runs and reading their captures
    definition = next(
        (r.report["traffic"]["definition"] for r in results.values() if r.report is not None),
        None,
    )
    result = {
        "bench": "traffic",
        "machine": {
            "nproc": len(os.sched_getaffinity(0)),
            "cpus": os.cpu_count(),
            "kernel": platform.release(),
            "python": platform.python_version(),
        },
        "beacon_interval_s": args.beacon,
        "stay_s": args.minutes * 60.0,
        "wall_s": round(wall, 1),
        "concurrency": (
            f"the {len(sizes)} fleets ran at the same time, each on its own lab (own namespaces "
            "and medium bridge); a lab's captures see only its own medium, so one fleet's "
            "bytes never include another's; only the CPU was shared"
        ),
        "counted": (
            "SDfR datagrams only (UDP port 1900, ARP apart), as the report's paper measure "
            "counts them, in two sizes: 'payload' = UDP payload bytes (the SDfR datagram, the "
            "figure the report compares with the paper) and 'frame' = whole Ethernet frame as "
            "captured (+42 bytes of Ethernet/IP/UDP headers, no preamble/FCS). Scaled to 5 min "
            "by 300 s / the measured window (start-up included). kB = 1000 bytes."
        ),
        "definition": definition,
        "paper_conditions": (
            f"the paper's figure 6 was measured under its own load ({paper.PAPER_CONDITIONS}, "
            "robots changing their services); these fleets publish 2 services each and change "
            "none: not comparable, and not set beside it ('make bench-paper' is)"
        ),
        "run_folder": str(folder),
        "fleets": fleets,
        "left_behind": left,
        "problems": problems,
    }
    text = json.dumps(result, indent=2)
    print(text, flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text + "\n")
    err("")
    if fleets:
        err(table(fleets))
    nproc = result["machine"]["nproc"]
    err(f"wall time {wall:.0f} s for {len(sizes)} fleets at once (nproc {nproc})")
    err(f"JSON: {args.out}")
    if problems:
        err("bench: FAILED\n  " + "\n  ".join(problems))
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
