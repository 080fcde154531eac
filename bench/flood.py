"""What a flood of fake robots costs a real daemon (an open fleet: the worst case).

Three robots at the product's 10 s beacon in one netlab lab and an outsider namespace on the
same medium. The outsider sends r1 fake robots' beacons (each fake from its own forged
address, so no per-source limit helps) at --rate datagrams a second for --seconds, after
--fakes distinct ones in one burst. Measured on r1, before and during the flood, in the same
run: CPU of the daemon's process tree (% of one core), its PSS, `/neighbors` latency over the
unix socket (p50, p99), the datagrams it sent (challenges are pings), its history map's size,
and whether r1 ever stopped listing r2 or r3 (sampled every 0.2 s).

JSON on stdout and in --out (runs/bench-flood.json). Needs root.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import threading
import time
from datetime import datetime
from pathlib import Path

from netlab import naming, procstat
from netlab.lab import Lab
from sdfr.client import Client

ROOT = Path(__file__).resolve().parent.parent
BEACON = 10.0


def metric(text: str, name: str) -> dict[str, float]:
    out = {}
    for m in re.finditer(rf"^{name}(\{{[^}}]*\}})? (\S+)$", text, re.M):
        out[m.group(1) or ""] = float(m.group(2))
    return out


def sent_total(client: Client) -> float:
    return sum(metric(client.metrics(), "sdfr_datagrams_total").get(k, 0.0) for k in (
        '{direction="out",type="discovery"}', '{direction="out",type="response"}',
        '{direction="out",type="update"}', '{direction="out",type="alive"}'))  # fmt: skip


def latencies(client: Client, seconds: float) -> list[float]:
    out = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        t0 = time.perf_counter()
        client.neighbors()
        out.append((time.perf_counter() - t0) * 1000)
        time.sleep(0.02)
    return out


def pct(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return round(ordered[min(len(ordered) - 1, int(q * len(ordered)))], 2)


class Lists:
    """Samples which of r2, r3 r1 lists, every 0.2 s."""

    def __init__(self, lab: Lab) -> None:
        self.lab = lab
        self.missed: list[tuple[float, list[str]]] = []
        self.samples = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        with Client(unix_socket=self.lab.robot("r1").api_socket, timeout=5.0) as c:
            while not self._stop.wait(0.2):
                seen = {n["robot_id"] for n in c.neighbors()}
                self.samples += 1
                missing = sorted({"r2", "r3"} - seen)
                if missing:
                    self.missed.append((time.monotonic(), missing))

    def __enter__(self) -> Lists:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(10)


def phase(lab: Lab, pid: int, seconds: float) -> dict[str, object]:
    """CPU and memory of r1's daemon, its /neighbors latency, what it sent, over `seconds`."""
    with Client(unix_socket=lab.robot("r1").api_socket, timeout=5.0) as c:
        sent0 = sent_total(c)
        start = procstat.Usage.read(procstat.tree(pid, procstat.children()))
        lat = latencies(c, seconds)
        end = procstat.Usage.read(procstat.tree(pid, procstat.children()))
        sent1 = sent_total(c)
        usage = procstat.window(start, end)
        return {
            "cpu_percent_of_one_core": usage["cpu_percent"],
            "pss_mib": usage["pss_mib"],
            "neighbors_ms": {"p50": pct(lat, 0.5), "p99": pct(lat, 0.99), "n": len(lat)},
            "datagrams_sent_per_s": round((sent1 - sent0) / usage["wall_s"], 1),
            "history_rows": len(c.history()),
        }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench.flood", description=__doc__.splitlines()[0])
    p.add_argument("--rate", type=float, default=5000.0, help="datagrams a second")
    p.add_argument("--seconds", type=float, default=60.0, help="how long the flood lasts")
    p.add_argument("--fakes", type=int, default=10_000, help="distinct fake robots")
    p.add_argument("--quick", action="store_true", help="a 15 s flood (a smoke run)")
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "bench-flood.json")
    args = p.parse_args(argv)
    if os.geteuid() != 0:
        print("bench.flood: needs root (robots are network namespaces)", file=sys.stderr)
        return 2
    seconds = 15.0 if args.quick else args.seconds
    name = naming.check_lab_name(f"fl{naming.b36(os.getpid() % 36**4, 4)}")
    with Lab(name) as lab:
        lab.add_robots(["r1", "r2", "r3", "x9"])
        lab.start_all(["r1", "r2", "r3"], beacon_interval=BEACON)
        time.sleep(3.0)
        pid = lab.daemon_pid("r1")
        assert pid is not None
        idle = phase(lab, pid, 10.0)
        net = ".".join(lab.robot("r1").ip.split(".")[:2])
        flood_argv = [
            sys.executable, "-m", "sdfr.testing.outsider", "flood", "--to", lab.robot("r1").ip,
            "--count", str(args.fakes), "--fleet", str(lab.fleet), "--net", net,
            "--rate", str(args.rate), "--seconds", str(seconds),
        ]  # fmt: skip
        with Lists(lab) as lists:
            flood = lab.popen("x9", flood_argv, cwd=ROOT, stdout=subprocess.PIPE, text=True)
            time.sleep(min(5.0, seconds / 4))  # let it build up
            during = phase(lab, pid, max(1.0, seconds - min(5.0, seconds / 4) - 1.0))
            out, _ = flood.communicate(timeout=seconds + 60)
            time.sleep(1.0)
        sent = json.loads(out.strip().splitlines()[-1])
        with Client(unix_socket=lab.robot("r1").api_socket) as c:
            rejects = metric(c.metrics(), "sdfr_rejects_total")
            challenges = metric(c.metrics(), "sdfr_challenges_total").get("", 0.0)
            status = c.health()["status"]
    result = {
        "bench": "flood",
        "started": datetime.now().isoformat(timespec="seconds"),
        "conditions": (
            f"3 robots at the {BEACON:.0f} s beacon, open fleet; an outsider sends r1 beacons of "
            f"{args.fakes} fake robots, each from its own forged address, at {args.rate:.0f}/s "
            f"for {seconds:.0f} s (sent {sent['sent']} in {sent.get('seconds', '?')} s)"
        ),
        "idle": idle,
        "flood": during,
        "r1_stopped_listing_a_peer": len(lists.missed),
        "list_samples": lists.samples,
        "challenges_sent": challenges,
        "rejects": {k.split('"')[1]: v for k, v in rejects.items() if '"' in k},
        "health_after": status,
        "issue_9_before": {
            "cpu_percent": 99,
            "neighbors_ms": "30-200 (from 1.5)",
            "pings_per_datagram_received": 2.1,
            "pss_mib": "54 -> 84 after 10,000 fakes",
        },
    }
    text = json.dumps(result, indent=2)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text + "\n")
    print(text)
    return 0 if not lists.missed else 1


if __name__ == "__main__":
    raise SystemExit(main())
