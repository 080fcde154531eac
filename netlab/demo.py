"""`make netlab`: a fleet of real sdfrd daemons in namespaces, through discovery, a partition
and a merge, with the medium captured and a report written under runs/.

Each phase waits for a condition with a deadline and prints how long it took;
the run ends with a summary table and the path of its report (JSON + PNG).
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from netlab.analysis import count_updates, neighbour_agreement, read_run
from netlab.capture import Capture, start_all, stop_all
from netlab.errors import NetlabError
from netlab.lab import Lab
from netlab.naming import BRIDGE
from netlab.ranges import UnitDisc
from netlab.report import AgreementSample, ConnectivitySample, write_report
from sdfr.client import Client
from sdfr.errors import ApiError

SERVICES = (("camera", "sensor.camera", {"fps": 30}), ("lidar", "sensor.lidar", {"hz": 10}))


@dataclass
class Phase:
    name: str
    deadline: float
    took: float | None = None
    detail: str = ""

    @property
    def ok(self) -> bool:
        return self.took is not None


class Observer:
    """Samples every robot's neighbour list against the medium's truth, in the background."""

    def __init__(self, lab: Lab, period: float = 0.25) -> None:
        self.lab = lab
        self.period = period
        self.clients = {
            name: Client(unix_socket=r.api_socket, timeout=2.0) for name, r in lab.robots.items()
        }
        self.connectivity: list[ConnectivitySample] = []
        self.agreement: list[AgreementSample] = []
        self.lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def seen(self, services: dict[str, set[str]] | None = None) -> dict[str, set[str]]:
        """Each robot's reachable peers; with `services`, only those whose services it lists
        are exactly those (robot -> service names)."""
        out: dict[str, set[str]] = {}
        with self.lock:
            for name, client in self.clients.items():
                try:
                    out[name] = {
                        n["robot_id"]
                        for n in client.neighbors()
                        if services is None
                        or {s["name"] for s in n["services"]} == services.get(n["robot_id"])
                    }
                except ApiError:
                    out[name] = set()
        return out

    def truth(self) -> dict[str, set[str]]:
        links = self.lab.links()
        return {name: {a for (a, b) in links if b == name} for name in self.clients}

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            now = time.time()
            truth, seen = self.truth(), self.seen()
            linked = {frozenset(p) for p in self.lab.links()}
            mutual = sum(1 for a in seen for b in seen[a] if a < b and a in seen.get(b, set()))
            self.connectivity.append(
                ConnectivitySample(now, len(linked), {a: len(s) for a, s in seen.items()}, mutual)
            )
            per_robot = {
                a: neighbour_agreement(
                    {a: truth[a], **{b: () for b in truth if b != a}}, {a: seen[a]}
                )
                for a in truth
            }
            self.agreement.append(AgreementSample(now, neighbour_agreement(truth, seen), per_robot))

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()
        for client in self.clients.values():
            client.close()


def wait_for(phase: Phase, pred: Callable[[], bool], say: Callable[[str], None]) -> None:
    start = time.monotonic()
    while time.monotonic() - start < phase.deadline:
        if pred():
            phase.took = time.monotonic() - start
            say(f"  ok   {phase.name}: {phase.took:.2f} s (deadline {phase.deadline:.1f} s)")
            return
        time.sleep(0.02)
    say(f"  FAIL {phase.name}: not within {phase.deadline:.1f} s")


def lists(obs: Observer, groups: Sequence[Sequence[str]]) -> bool:
    """Each robot lists exactly the others of its group, each with its services."""
    services = {r: {f"{r} {name}" for name, _, _ in SERVICES} for g in groups for r in g}
    seen = obs.seen(services)
    for group in groups:
        for a in group:
            if seen[a] != set(group) - {a}:
                return False
    return True


def run(args: argparse.Namespace) -> int:
    say = print
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    run_dir = Path(args.runs).resolve() / f"netlab-{stamp}"
    run_dir.mkdir(parents=True, exist_ok=True)
    names = [f"r{i}" for i in range(1, args.robots + 1)]
    half = len(names) // 2
    side_a, side_b = names[:half], names[half:]
    beacon = args.beacon
    phases = [
        Phase("discovery: all list all, with services published", 2.0),
        Phase(
            f"partition {{{','.join(side_a)}}} | {{{','.join(side_b)}}}: each side alone",
            3 * beacon + 0.5,
        ),
        Phase("merge: all list all again", beacon + 1.0),
    ]
    say(
        f"netlab demo: {len(names)} robots, beacon {beacon} s (the product default is 10 s), "
        f"run folder {run_dir}"
    )
    t_start = time.time()
    with Lab("demo", seed=args.seed, workdir=run_dir / "lab", range_model=UnitDisc(100.0)) as lab:
        t0 = time.monotonic()
        with lab.batch():
            for i, name in enumerate(names):
                lab.add_robot(name, pos=(2.0 * i, 0.0))
        say(f"  lab up: {len(names)} namespaces on one medium in {time.monotonic() - t0:.2f} s")
        captures = [Capture(lab.medium.ns, BRIDGE, run_dir / "medium.pcap", label="medium")]
        captures += [
            Capture(r.ns, "eth0", run_dir / f"{name}.pcap", label=name)
            for name, r in lab.robots.items()
        ]
        start_all(captures)
        obs = Observer(lab)
        obs.start()  # before the daemons, so the plots show discovery itself
        try:
            lab.start_all(beacon_interval=beacon)
            say(f"  {len(names)} daemons healthy")
            for name in names:
                client = lab.client(name)
                for sname, stype, attrs in SERVICES:
                    client.publish(f"{name} {sname}", stype, attributes=attrs)
            wait_for(phases[0], lambda: lists(obs, [names]), say)
            lab.partition([side_a, side_b])
            wait_for(phases[1], lambda: lists(obs, [side_a, side_b]), say)
            time.sleep(beacon)
            merged_wall = time.time()
            lab.merge()
            wait_for(phases[2], lambda: lists(obs, [names]), say)
            time.sleep(1.0)
        finally:
            obs.stop()
            stop_all(captures)
    records = read_run(run_dir)
    refetched = count_updates(records, since=merged_wall)
    phases[2].detail = f"{refetched} Update datagrams after the merge (0: nothing re-fetched)"
    report = write_report(
        run_dir,
        records=records,
        connectivity_samples=obs.connectivity,
        agreement_samples=obs.agreement,
        meta={
            "scenario": "discovery, partition, merge",
            "robots": len(names),
            "beacon_interval_s": beacon,
            "start": t_start,
            "end": time.time(),
            "phases": [
                {"name": p.name, "deadline_s": p.deadline, "took_s": p.took} for p in phases
            ],
        },
    )
    say("")
    say(f"{'phase':58} {'deadline':>9} {'took':>8}  result")
    for p in phases:
        took = f"{p.took:.2f} s" if p.took is not None else "-"
        say(f"{p.name:58} {p.deadline:>7.1f} s {took:>8}  {'ok' if p.ok else 'FAILED'}")
    say(f"\nmerge: {phases[2].detail}")
    files = sorted(f.name for f in run_dir.iterdir() if f.suffix in (".json", ".png"))
    say(f"report: {run_dir} ({', '.join(files)})")
    _ = report
    return 0 if all(p.ok for p in phases) and refetched == 0 else 1


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m netlab.demo", description=__doc__)
    p.add_argument("--robots", type=int, default=6)
    p.add_argument("--beacon", type=float, default=1.0, help="beacon interval in seconds")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--runs", default="runs", help="folder for the run's report")
    args = p.parse_args(argv)
    try:
        return run(args)
    except NetlabError as exc:
        print(f"netlab: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())


__all__: list[Any] = ["main"]
