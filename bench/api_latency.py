"""API latency under the paper's load (its Figure 4), plus CPU and memory (its Figure 5).

For each fleet size (the paper's 2, 4 and 6 robots) a fleet of real sdfrd
daemons runs in network namespaces. Robots 2..n each publish 100 services;
robot 1 carries the paper's per-robot load — 70 publishers churning
(publish, unpublish after a random delay, publish again) and 30 consumers
polling the neighbour table in parallel threads — over its TCP API.

Two modes per fleet size: "paced", each consumer asking about every 50 ms
(30 consumers: 600 requests/s), where the latency is the daemon's service
time; and "closed_loop", every consumer asking again the moment it has its
answer, where on a 2-core machine shared by the daemon and a 100-thread
load generator the latency is mostly queueing (Little's law: 30 requests in
flight / throughput), so its throughput is the figure to read. The result
is JSON on stdout (and in the file given with --out).

Needs root (network namespaces). The paper measured 95-130 ms to publish,
98-122 ms to unpublish and under 5 ms for the neighbour table.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from netlab import procstat
from netlab.lab import Lab
from sdfr.host import procfs

PAPER = {
    "publish_ms": [95, 130],
    "unpublish_ms": [98, 122],
    "neighbors_ms_max": 5,
    "cpu_percent": [2.2, 2.8],
    "memory_percent_of_4GB_max": 0.3,
}


def proc_tree(root: int) -> list[int]:
    """`root` and its descendants."""
    return procfs.tree(root, procfs.parent_map())


def cpu_and_rss(pids: list[int]) -> tuple[float, int]:
    """Total CPU seconds and resident bytes of `pids`."""
    usage = procstat.Usage.read(pids)
    return usage.cpu_s, usage.rss_kb * 1024


def wait(what: str, pred: Any, timeout: float) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            if pred():
                return
        except Exception:
            pass
        time.sleep(0.05)
    raise SystemExit(f"bench: {what} not within {timeout} s")


def run_fleet(n: int, args: argparse.Namespace, tmp: Path) -> dict[str, object]:
    with Lab(f"bench{n}", workdir=tmp / f"n{n}") as lab:
        names = [f"r{i}" for i in range(1, n + 1)]
        lab.add_robots(names)
        lab.start_all()  # the product's defaults: 10 s beacon
        for name in names[1:]:
            client = lab.client(name)
            for k in range(100):
                client.publish(
                    f"{name} service {k}",
                    f"bench.kind{k % 7}",
                    f"http://{name}:9000/{k}",
                    {"index": k, "frame": f"{name}/base_link"},
                )
        first = lab.client("r1")
        wait(
            "robot 1 lists every robot with 100 services",
            lambda: sorted(len(x["services"]) for x in first.neighbors()) == [100] * (n - 1),
            30,
        )
        supervisor = json.loads((lab.robot("r1").state_dir / "layers.json").read_text())
        return {
            "robots": n,
            "modes": {
                mode: measure(lab, int(supervisor["supervisor"]), args, interval)
                for mode, interval in (("paced", args.poll_interval), ("closed_loop", 0.0))
            },
        }


def measure(lab: Lab, daemon_pid: int, args: argparse.Namespace, interval: float) -> Any:
    """Run the load generator inside robot 1; add the daemon's CPU and memory meanwhile."""
    cpu0, _ = cpu_and_rss(proc_tree(daemon_pid))
    rss_peak = 0
    t0 = time.monotonic()
    stop = threading.Event()

    def sample() -> None:
        nonlocal rss_peak
        while not stop.wait(0.5):
            rss_peak = max(rss_peak, cpu_and_rss(proc_tree(daemon_pid))[1])

    sampler = threading.Thread(target=sample)
    sampler.start()
    try:
        res = lab.exec(
            "r1",
            [
                sys.executable,
                "-m",
                "bench.load",
                "--duration",
                str(args.duration),
                "--speedup",
                str(args.speedup),
                "--publishers",
                str(args.publishers),
                "--consumers",
                str(args.consumers),
                "--poll-interval",
                str(interval),
            ],
            timeout=args.duration + 60,
            cwd=str(Path(__file__).resolve().parent.parent),
        )
    finally:
        stop.set()
        sampler.join()
    elapsed = time.monotonic() - t0
    daemon = proc_tree(daemon_pid)
    cpu1, rss = cpu_and_rss(daemon)
    if res.returncode != 0:
        raise SystemExit(f"bench: load generator failed: {res.stderr.strip()[-500:]}")
    load = json.loads(res.stdout)
    return {
        "consumer_poll_interval_s": interval,
        **load,
        "daemon_cpu_percent_of_one_core": round(100 * (cpu1 - cpu0) / elapsed, 1),
        "daemon_rss_mb": round(max(rss, rss_peak) / 2**20, 1),
        "daemon_processes": len(daemon),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--robots", default="2,4,6", help="fleet sizes, comma-separated")
    p.add_argument("--duration", type=float, default=20.0, help="seconds of load per fleet size")
    p.add_argument(
        "--speedup",
        type=float,
        default=10.0,
        help="divide the paper's publish/unpublish delays by this (more samples)",
    )
    p.add_argument("--publishers", type=int, default=70)
    p.add_argument("--consumers", type=int, default=30)
    p.add_argument(
        "--poll-interval",
        type=float,
        default=0.05,
        help="mean pause between one consumer's requests in the paced mode",
    )
    p.add_argument("--out", type=Path, help="also write the JSON here")
    args = p.parse_args(argv)
    if os.geteuid() != 0:
        print("bench: needs root (it runs robots in network namespaces)", file=sys.stderr)
        return 2
    runs = []
    with tempfile.TemporaryDirectory(prefix="sdfr-bench-") as tmp:
        for n in (int(x) for x in args.robots.split(",")):
            print(f"bench: {n} robots ...", file=sys.stderr, flush=True)
            runs.append(run_fleet(n, args, Path(tmp)))
    result = {
        "bench": "api-latency",
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "load": {
            "publishers": args.publishers,
            "consumers": args.consumers,
            "duration_s": args.duration,
            "publish_delay_s": 10.0 / args.speedup,
            "unpublish_delay_max_s": 5.0 / args.speedup,
            "services_per_other_robot": 100,
        },
        "paper": PAPER,
        "target_p50_ms": 2.0,
        "runs": runs,
    }
    text = json.dumps(result, indent=2)
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
