"""Latency from ~/publish on one robot to the change on ~/neighbors of another (ROS 2).

Two netlab robots, each running sdfrd (beacon --beacon seconds) and the ROS 2 node `sdfr`
(rclpy, Fast DDS inside the robot), and a probe on each (tests/ros/probe_ros2.py). The probe
on r1 publishes a service through /sdfr/publish, then unpublishes it: --changes changes in
all, one at a time, after a random pause. Each latency is from just before r1's probe
publishes to the moment r2's probe receives the first /sdfr/neighbors message showing the
change (both clocks are the host's). It is the sum of DDS on r1, the node's REST call,
sdfrd's delta datagram, r2's sdfrd telling its change stream (GET /events), r2's node
reading the list again, and DDS on r2. (`poll_interval`, set with --poll, matters only to a
node whose sdfrd has no change stream.)

JSON on stdout and in --out (runs/bench-ros.json). Needs root and .venv/ros2
(make ros-setup).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import statistics
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path
from typing import Any

from netlab import naming
from netlab.lab import Lab
from sdfr.testing.ros import Probe, Proc, ros2_environ

ROOT = Path(__file__).resolve().parent.parent
ROS2_PY = ROOT / ".venv" / "ros2" / "bin" / "python"
#: The ROS tests' probe (run as a script, not imported).
PROBE = ROOT / "tests" / "ros" / "probe_ros2.py"


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))]


def summary(ms: list[float]) -> dict[str, float]:
    return {
        "n": len(ms),
        "p50_ms": round(statistics.median(ms), 1),
        "p90_ms": round(percentile(ms, 0.9), 1),
        "max_ms": round(max(ms), 1),
        "mean_ms": round(statistics.fmean(ms), 1),
    }


def measure(lab: Lab, poll: float, changes: int, tmp: Path, seed: int = 1) -> dict[str, Any]:
    """`changes` changes at one polling interval: publish/unpublish pairs on r1, seen on r2."""
    base = 2 * (os.getpid() % 50)
    envs = {"r1": ros2_environ(base), "r2": ros2_environ(base + 1)}
    argv = [str(ROS2_PY), "-m", "sdfr.ros.ros2", "--ros-args", "-p", f"poll_interval:={poll}"]
    nodes = [Proc(lab, r, argv, envs[r], tmp / f"node-{r}-{poll}.log") for r in envs]
    probes = [Probe(lab, r, ROS2_PY, PROBE, envs[r], tmp / f"probe-{r}-{poll}.log") for r in envs]
    p1, p2 = probes
    rng = random.Random(seed)
    published: list[float] = []
    unpublished: list[float] = []
    try:
        p1.call("ready")
        p2.call("ready")
        p2.call("wait_neighbors", robot="r1")
        for i in range(changes):
            service = {"name": f"bench-{i // 2}", "type": "bench.service"}
            op = "publish" if i % 2 == 0 else "unpublish"
            sent = p1.call(op, service=service)["t"]
            seen = p2.call(
                "wait_neighbors", robot="r1", name=service["name"], present=op == "publish",
                since=sent, timeout=30,
            )  # fmt: skip
            (published if op == "publish" else unpublished).append((seen["t"] - sent) * 1000)
            # A random pause of up to one poll interval: r2's node polls on its own clock,
            # and a fixed pause would lock every change to the same phase of its polling.
            time.sleep(0.05 + rng.uniform(0.0, poll))
    finally:
        for probe in probes:
            probe.close()
        for node in nodes:
            node.stop()
    return {
        "poll_interval_s": poll,
        "all": summary(published + unpublished),
        "publish": summary(published),
        "unpublish": summary(unpublished),
        "samples_ms": [round(x, 1) for x in published + unpublished],
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench.ros_latency", description=__doc__.splitlines()[0])
    p.add_argument("--changes", type=int, default=50, help="changes measured per setting")
    p.add_argument("--beacon", type=float, default=1.0, help="sdfrd's beacon interval (s)")
    p.add_argument("--poll", type=float, nargs="+", default=[0.25], help="node poll intervals (s)")
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "bench-ros.json")
    args = p.parse_args(argv)
    if os.geteuid() != 0:
        print("bench.ros_latency: needs root (robots are network namespaces)", file=sys.stderr)
        return 2
    if not ROS2_PY.exists():
        print("bench.ros_latency: no .venv/ros2: run make ros-setup first", file=sys.stderr)
        return 2
    name = naming.check_lab_name(f"rl{naming.b36(os.getpid() % 36**4, 4)}")
    runs = []
    with tempfile.TemporaryDirectory(prefix="bench-ros-") as tmp, Lab(name) as lab:
        lab.add_robots(["r1", "r2"])
        lab.start_all(beacon_interval=args.beacon)
        for poll in args.poll:
            runs.append(measure(lab, poll, args.changes, Path(tmp)))
    result = {
        "bench": "ros_latency",
        "when": datetime.now().isoformat(timespec="seconds"),
        "what": "ms from ~/publish (or ~/unpublish) on r1 to the change on ~/neighbors of r2",
        "ros": "ROS 2 Kilted wheels, rclpy, Fast DDS (UDPv4, each robot's loopback)",
        "beacon_interval_s": args.beacon,
        "runs": runs,
    }
    text = json.dumps(result, indent=2)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
