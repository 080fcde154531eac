"""`make netlab`: bundled scenarios on fleets of real sdfrd daemons in namespaces.

Runs, one after the other, with `netlab.scenario`: a static fleet of 6 robots (issue 4,
check 1), partition and merge (check 5) and random-waypoint mobility (check 8, 30 s instead of
2 minutes unless --full).  Each prints its progress and its checks, and writes its folder in
the demo's run folder runs/netlab-<time>/ (pcaps, report.json, PNG plots, daemon logs); the
demo ends with a table across scenarios, also written there as summary.json.  Exit status 0
when every check of every scenario passed.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from datetime import datetime
from pathlib import Path

from netlab import scenario
from netlab.errors import NetlabError

SCENARIOS = ("static-6", "partition-merge", "mobility")


def summary(results: list[scenario.RunResult], cwd: Path) -> list[str]:
    lines = [f"{'scenario':18} {'robots':>6} {'beacon':>7} {'checks':>7} {'time':>8}  result  run"]
    for r in results:
        ok = sum(c.ok is True for c in r.checks)
        folder = "-"
        if r.run_dir is not None:
            folder = str(r.run_dir.relative_to(cwd) if r.run_dir.is_relative_to(cwd) else r.run_dir)
        result = r.status if r.status != "skipped" else f"skipped: {r.reason}"
        lines.append(
            f"{r.scenario:18} {r.robots:>6} {r.beacon:>5g} s {ok:>3}/{len(r.checks):<3} "
            f"{r.duration:>6.1f} s  {result:6}  {folder}"
        )
    return lines


def run(args: argparse.Namespace) -> int:
    names = args.only or list(SCENARIOS)
    quick = not args.full
    print(
        f"netlab demo: {', '.join(names)}{' (quick: mobility 30 s)' if quick else ''}; "
        "real sdfrd daemons in network namespaces, beacon 1 s (the product default is 10 s)",
        flush=True,
    )
    t0 = time.monotonic()
    folder = Path(args.runs) / f"netlab-{datetime.now():%Y%m%d-%H%M%S}"
    results = []
    for name in names:
        print("", flush=True)
        sc = scenario.load(scenario.find(name))
        results.append(scenario.run(sc, run_dir=folder / name, quick=quick))
    took = time.monotonic() - t0
    print("")
    for line in summary(results, Path.cwd()):
        print(line)
    passed = sum(r.ok for r in results)
    print(f"\n{passed} of {len(results)} scenarios passed in {took:.0f} s")
    record = {
        "passed": passed == len(results),
        "duration_s": round(took, 1),
        "quick": quick,
        "scenarios": [r.to_json() for r in results],
    }
    (folder / "summary.json").write_text(json.dumps(record, indent=1) + "\n")
    print(f"reports: {folder}/<scenario>/report.json and *.png; summary: {folder}/summary.json")
    return 0 if passed == len(results) else 1


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m netlab.demo", description=__doc__)
    p.add_argument("--runs", default="runs", help="folder for the run folders (default runs/)")
    p.add_argument("--full", action="store_true", help="full durations (mobility 2 min)")
    p.add_argument(
        "--only",
        nargs="+",
        metavar="NAME",
        choices=sorted(scenario.bundled()),
        help="run these bundled scenarios instead",
    )
    args = p.parse_args(argv)
    try:
        return run(args)
    except NetlabError as exc:
        print(f"netlab: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
