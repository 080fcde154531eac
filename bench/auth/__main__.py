"""`python -m bench.auth`: the measures run, their JSON written, the table printed."""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from datetime import datetime
from pathlib import Path
from typing import Any

import bench.auth
from bench.auth.baseline import core_identity, run_baseline, run_with_core, side_by_side
from bench.auth.datagrams import bytes_per_datagram, receive_cpu, seal_and_check_cpu, update_parts
from bench.auth.dynamics import dynamics
from bench.auth.fixtures import FIVE_MINUTES_S, ROOT
from bench.auth.fleet import fleet_bytes
from bench.auth.report import report


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="bench.auth", description=(bench.auth.__doc__ or "").splitlines()[0]
    )
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "bench-auth.json")
    p.add_argument("--quick", action="store_true", help="fewer iterations (CI smoke run)")
    p.add_argument(
        "--baseline",
        metavar="REV|DIR",
        help="also run this bench against the sdfr of a git revision or a checkout, and put "
        "both side by side",
    )
    p.add_argument(
        "--core",
        metavar="REV|DIR",
        help="measure the sdfr of this git revision or checkout rather than the one imported "
        "(the bench code stays this checkout's)",
    )
    p.add_argument("--seeds", type=int, help="seeds of the join and restart runs (default 12)")
    args = p.parse_args(argv)
    if args.core:
        child = ["--out", str(args.out.resolve())]
        child += ["--quick"] if args.quick else []
        if args.baseline:
            base = Path(args.baseline)
            child += ["--baseline", str(base.resolve()) if base.exists() else args.baseline]
        child += ["--seeds", str(args.seeds)] if args.seeds else []
        return run_with_core(args.core, child)
    n, repeats = (2_000, 3) if args.quick else (20_000, 7)
    seeds = args.seeds or (4 if args.quick else 12)
    bytes_seeds, window = (1, 120.0) if args.quick else (3, FIVE_MINUTES_S)
    started = datetime.now().isoformat(timespec="seconds")
    t_wall = time.perf_counter()
    ident = core_identity()
    print(f"bench.auth: sdfr {ident['sdfr']} at {ident['git']}", file=sys.stderr)
    result: dict[str, Any] = {
        "bench": "auth",
        "started": started,
        "core": ident,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "bytes_per_datagram": bytes_per_datagram(),
        "update_parts": update_parts(),
        "cpu_per_datagram": seal_and_check_cpu(n, repeats),
        "receive_path": receive_cpu(n // 4, repeats),
        "fleet": fleet_bytes(6, 100, 60.0 if args.quick else FIVE_MINUTES_S),
        "dynamics": dynamics(seeds, bytes_seeds, window),
    }
    result["wall_s"] = round(time.perf_counter() - t_wall, 1)
    if args.baseline:
        child = ["--seeds", str(seeds)] + (["--quick"] if args.quick else [])
        old = run_baseline(args.baseline, child)
        result["baseline"] = old
        result["side_by_side"] = side_by_side(old, result)
    text = json.dumps(result, indent=2)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text + "\n")
    print(text)
    report(result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
