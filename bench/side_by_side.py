"""SDfR beside the systems robotics teams would choose instead, on one lab, under one load, in
one run.

Every robot runs them all at once: sdfrd at the product's defaults (10 s beacon) with its
services published through the REST API, and a node of each peer (`bench.peers`: python-zeroconf
and Avahi for mDNS / DNS-SD, Zenoh in peer mode, ROS 2's own discovery on Fast DDS, each with its
defaults or a labelled liveness knob) that registers the same services and lists the others'.
All churn the same way (`bench.paper_load`'s reading of the paper: 70 publishers, one unpublish
every 0-5 s, each publisher publishing again 10 s later), and each robot has a watcher per
system that notes when a service of another robot is listed and when it is not any more, told
through each system's own notifications (SDfR: `GET /events` on the robot; a peer: its node's
callbacks, a service counting once its attributes are known).  All act at the same instants,
and the same pcaps hold every system's traffic (each peer's ports: `bench.peers`; two systems
on one port, python-zeroconf and Avahi, never run in one lab), so every figure is measured like
for like.  `--loss` puts the same loss (in %) on every pair of robots.

The steps, timed for every system from the moment they were asked:

1. start-up: daemons / nodes started together, each publishing its 70 services at once:
   until every robot lists every service of every other;
2. churn (5 minutes; `--quick`: 30 s): bytes per robot on the air, CPU and PSS per robot,
   and how long each change took to be listed elsewhere;
3. a new service on r1: until every other robot lists it;
4. a graceful leave (SIGTERM) of the last robot: until no robot lists the services it had
   when it left (a service it had unpublished earlier that a robot still lists, which
   python-zeroconf can do for the records' TTL when a goodbye overtakes an answer sent just
   before it, is counted apart: `stale_after_leave`);
5. a silent death (SIGKILL) of the one before: until no robot lists its services, waiting at
   most `KILL_CAP` s (python-zeroconf keeps an unannounced service until its PTR record
   expires, 75 minutes by default; to Zenoh a killed process is no silent departure: the
   kernel closes its TCP sessions; DDS waits out the participant's lease, 20 s by default);
6. a 40 s partition of the robots left into two halves, during which r1 publishes a service
   and a robot of the other half unpublishes one: whether and when each half stopped listing
   the other, and after the merge until every list is right again.

`make bench-paper` runs it after the paper's runs; `python -m bench.side_by_side` runs it alone.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import itertools
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from bench import change_path, err, floor, paper_lab
from bench.listed import (
    everyone_lists,
    everyone_lists_one,
    first_time,
    halves_apart,
    nobody_lists,
    nobody_lists_these,
    own_services,
    replay,
)
from bench.paper_lab import ROOT, Sampler, captured, conditions, keep_logs
from bench.paper_measure import (
    ip_traffic,
    mdns_messages,
    per_5_min,
    propagation,
    read_events,
    spread,
)
from bench.peers import DEFAULT as DEFAULT_PEERS
from bench.peers import PEERS, SDFR_FLOWS, Peer, capture_filter, chosen
from bench.peers_report import growth_figure, markdown, table
from netlab import naming
from netlab.lab import Lab
from netlab.ranges import check_loss
from sdfr import __version__ as sdfr_version

PUBLISHERS = 70


@dataclass(frozen=True, slots=True)
class Timing:
    """How long each step lasts (seconds) and at what beacon SDfR runs."""

    robots: int = 6
    beacon: float = 10.0  # the product's
    settle: float = 30.0  # start-up, before the churn
    churn: float = 300.0
    look: float = 15.0  # after a new service and after a leave
    kill_cap: float = 120.0
    partition: float = 40.0
    after_merge: float = 60.0
    loss: float = 0.0  # % on every pair of robots, both ways (netlab's pair loss)


FULL = Timing()
QUICK = Timing(robots=4, churn=30.0, kill_cap=40.0)
#: Every step for seconds, at a 1 s beacon, so that CI runs all of it (`make test`): its
#: numbers mean nothing.
SMOKE = Timing(
    robots=4, beacon=1.0, settle=12.0, churn=8.0, look=4.0, kill_cap=8.0, partition=6.0,
    after_merge=8.0,
)  # fmt: skip


class Fleet:
    """SDfR and its peers on one lab: their processes, event files and what they published."""

    def __init__(
        self, lab: Lab, folder: Path, names: Sequence[str], seed: int, peers: Sequence[Peer]
    ) -> None:
        self.lab = lab
        self.folder = folder
        self.names = list(names)
        self.seed = seed
        self.peers = list(peers)
        self.systems = ["sdfr", *(p.name for p in peers)]
        self.nodes: dict[str, dict[str, subprocess.Popen[bytes]]] = {p.name: {} for p in peers}
        self.loaders: dict[str, subprocess.Popen[bytes]] = {}
        self.watchers: dict[str, subprocess.Popen[bytes]] = {}
        self.extra_events: list[dict[str, Any]] = []

    def path(self, system: str, kind: str, robot: str) -> Path:
        return self.folder / f"{system}-{kind}-{robot}.jsonl"

    def events(self, system: str) -> list[dict[str, Any]]:
        kinds = ("loader", "watcher") if system == "sdfr" else ("node",)
        files = [self.path(system, k, r) for k in kinds for r in self.names]
        out = read_events(p for p in files if p.exists())
        if system == "sdfr":
            out += [e for e in self.extra_events]
            out.sort(key=lambda e: float(e["t"]))
        return out

    def start_peer(self, peer: Peer, start_at: float, churn: tuple[float, float]) -> None:
        common = ["--publishers", str(PUBLISHERS), "--start-at", repr(start_at),
                  "--churn-at", repr(churn[0]), "--churn-until", repr(churn[1]),
                  "--seed", str(self.seed)]  # fmt: skip
        for name in self.names:
            events = str(self.path(peer.name, "node", name))
            self.nodes[peer.name][name] = self.lab.popen(
                name, peer.argv(name, self.lab.robot(name).ip, events, *common),
                cwd=str(ROOT), stdout=subprocess.DEVNULL, stderr=self._log(f"{peer.name}-{name}"),
            )  # fmt: skip

    def signal_peers(self, robot: str, sig: int) -> None:
        """`sig` to every peer's node on `robot` (SIGUSR1: one more service, SIGUSR2: one fewer,
        SIGTERM: leave, SIGKILL: die)."""
        for nodes in self.nodes.values():
            os.kill(nodes[robot].pid, sig)

    def _log(self, name: str) -> Any:
        return open(self.folder / f"{name}.log", "ab")

    def start_sdfr_load(self, churn: tuple[float, float]) -> None:
        for name in self.names:
            common = [sys.executable, "-m", "bench.paper_load", "--robot", name, "--consumers", "0"]
            self.watchers[name] = self.lab.popen(
                name,
                [*common, "--publishers", "0", "--duration", "86400", "--watch-events",
                 "--events", str(self.path("sdfr", "watcher", name))],
                cwd=str(ROOT), stdout=subprocess.DEVNULL, stderr=self._log(f"sdfr-watcher-{name}"),
            )  # fmt: skip
            self.loaders[name] = self.lab.popen(
                name,
                [*common, "--publishers", str(PUBLISHERS), "--first-delay", "0",
                 "--watch-interval", "0", "--churn-at", repr(churn[0]),
                 "--churn-until", repr(churn[1]), "--duration", repr(churn[1] - time.time() + 5),
                 "--seed", str(self.seed), "--events", str(self.path("sdfr", "loader", name))],
                cwd=str(ROOT), stdout=subprocess.DEVNULL, stderr=self._log(f"sdfr-loader-{name}"),
            )  # fmt: skip

    def stop_all(self) -> None:
        procs = [*self.watchers.values(), *self.loaders.values()]
        procs += [p for nodes in self.nodes.values() for p in nodes.values()]
        for proc in procs:
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(proc.pid, signal.SIGTERM)
        for proc in procs:
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(proc.pid, signal.SIGKILL)
                proc.wait()


def run(
    folder: Path,
    timing: Timing = FULL,
    *,
    seed: int = 1,
    peers: Sequence[str] = DEFAULT_PEERS,
) -> dict[str, Any]:
    """The side-by-side run of SDfR and `peers` (names of `bench.peers.PEERS`); its result
    (with `table`, the docs' table).  ValueError when a peer is unknown or cannot run here."""
    beside = chosen(peers)
    folder.mkdir(parents=True, exist_ok=True)
    n = timing.robots
    names = [f"r{i}" for i in range(1, n + 1)]
    result: dict[str, Any] = {
        "robots": n,
        "publishers_per_robot": PUBLISHERS,
        "timing_s": asdict(timing),
        "churn_s": timing.churn,
        "kill_cap_s": timing.kill_cap,
        "partition_s": timing.partition,
        "sdfr_beacon_s": timing.beacon,
        "systems": {
            "sdfr": {
                "label": f"SDfR {sdfr_version}",
                "knob": f"its defaults (beacon {timing.beacon:g} s)",
            },
            **{p.name: {"label": f"{p.label} {p.version()}", "knob": p.knob} for p in beside},
        },
        "conditions_before": conditions(),
        "problems": [],
    }
    lab_name = naming.unique_lab_name("z")
    labels = ", ".join(v["label"] for v in result["systems"].values())
    err(f"bench-paper: side-by-side: lab {lab_name}, {n} robots: {labels}")
    flows = [*SDFR_FLOWS, *(f for p in beside for f in p.flows)]
    with Lab(lab_name, seed=seed) as lab:
        lab.add_robots(names, {r: (2.0 + i, 5.0) for i, r in enumerate(names)})
        if timing.loss:
            for a, b in itertools.combinations(names, 2):
                lab.set_pair_quality(a, b, loss=timing.loss)
        fleet = Fleet(lab, folder, names, seed, beside)
        result["floor"] = {"idle": floor.measure(lab, names[0], names[1], folder)}
        try:
            with captured(lab, folder, capture_filter(flows)):
                result.update(steps(lab, fleet, names, timing))
        finally:
            fleet.stop_all()
            keep_logs(lab, folder)
    result["conditions_after"] = conditions()
    if "churn_window" in result:  # where SDfR's time went, from the pcaps (closed by now)
        start, end = result["churn_window"]
        result["sdfr_change_path"] = change_path.decompose(folder, names, (start, end))
    result["table"] = table(result)
    return result


def steps(lab: Lab, fleet: Fleet, names: list[str], timing: Timing) -> dict[str, Any]:
    out: dict[str, Any] = {}
    look, kill_cap = timing.look, timing.kill_cap
    # 1. start-up, both at once.
    t0 = time.time()
    churn = (t0 + timing.settle, t0 + timing.settle + timing.churn)
    out["churn_window"] = list(churn)
    for peer in fleet.peers:
        fleet.start_peer(peer, t0 + 0.5, churn)
    lab.start_all(beacon_interval=timing.beacon)
    fleet.start_sdfr_load(churn)
    time.sleep(max(0.0, churn[0] - time.time()))
    startup: dict[str, Any] = {}
    for system in fleet.systems:
        ev = fleet.events(system)
        initial = {r: own_services(ev, r, churn[0]) for r in names}
        startup[system] = first_time(ev, t0, churn[0], everyone_lists(names, initial))
    out["startup_s"] = startup
    # 2. churn: resources and bytes.
    roots = {f"sdfr-{r}": pid for r in names if (pid := lab.daemon_pid(r)) is not None}
    roots |= {f"{s}-{r}": p.pid for s, nodes in fleet.nodes.items() for r, p in nodes.items()}
    sampler = Sampler(roots)
    sampler.start()
    time.sleep(max(0.0, (churn[0] + churn[1]) / 2 - time.time()))
    out["floor_under_load"] = floor.measure(lab, names[0], names[1], fleet.folder)
    time.sleep(max(0.0, churn[1] - time.time()))
    sampler.stop()
    use = sampler.result()
    out["resources"] = {
        system: {
            "per_robot": {r: use.get(f"{system}-{r}", {}) for r in names},
            "cpu_percent": spread(use.get(f"{system}-{r}", {}).get("cpu_percent") for r in names),
            "pss_mib": spread(use.get(f"{system}-{r}", {}).get("pss_mib_max") for r in names),
        }
        for system in fleet.systems
    }
    time.sleep(12.0)  # republishes of the last seconds of churn, and their announcements
    macs = {r: lab.robot(r).mac for r in names}
    out["traffic"] = churn_traffic(fleet, macs, churn)
    out["seen_by_peers"] = {
        system: propagation(
            fleet.events(system), names, since=churn[0], until=churn[1], start="asked"
        )
        for system in fleet.systems
    }
    # 3. a new service on r1.
    t = time.time()
    fleet.extra_events.append({"t": t, "op": "publish", "robot": "r1", "sid": "extra1"})
    lab.client("r1").publish("extra", "bench.extra", service_id="extra1")
    fleet.signal_peers("r1", signal.SIGUSR1)
    time.sleep(look)
    others = names[1:]
    out["new_service_s"] = {
        system: first_time(
            fleet.events(system),
            t,
            t + look,
            everyone_lists_one(others, "r1", ("extra1", "p1001x")),
        )
        for system in fleet.systems
    }
    # 4. a graceful leave of the last robot: its services at the leave; apart, what the others
    # still list of those it had unpublished before.
    leaver, victim = names[-1], names[-2]
    left = names[:-1]
    t = time.time()
    lab.stop(leaver)
    fleet.signal_peers(leaver, signal.SIGTERM)
    time.sleep(look)
    out["graceful_leave_s"], out["stale_after_leave"] = {}, {}
    for system in fleet.systems:
        ev = fleet.events(system)
        had = own_services(ev, leaver, t)
        out["graceful_leave_s"][system] = first_time(
            ev, t, t + look, nobody_lists_these(left, leaver, had)
        )
        listed = replay(ev, t + look)
        out["stale_after_leave"][system] = sorted(
            [w, sid]
            for w in left
            for r, sid in listed.get(w, set())
            if r == leaver and sid not in had
        )
    # 5. a silent death, waited for at most kill_cap.
    alive = names[:-2]
    t = time.time()
    lab.kill(victim)
    fleet.signal_peers(victim, signal.SIGKILL)
    end = t + kill_cap
    while time.time() < end:
        done = [
            first_time(fleet.events(s), t, end, nobody_lists(alive, [victim]))
            for s in fleet.systems
        ]
        if all(d is not None for d in done):
            break
        time.sleep(2.0)
    out["kill_9_s"] = {
        system: first_time(fleet.events(system), t, end, nobody_lists(alive, [victim]))
        for system in fleet.systems
    }
    # 6. a 40 s partition of the rest into two halves, with a change on each side.
    half = len(alive) // 2
    a, b = alive[:half], alive[half:]
    tp = time.time()
    lab.partition([a, b])
    time.sleep(min(5.0, timing.partition / 4))
    fleet.extra_events.append({"t": time.time(), "op": "publish", "robot": a[0], "sid": "apart1"})
    lab.client(a[0]).publish("apart", "bench.extra", service_id="apart1")
    fleet.signal_peers(a[0], signal.SIGUSR1)
    gone_sid = next(s["id"] for s in lab.client(b[0]).services())
    fleet.extra_events.append(
        {"t": time.time(), "op": "unpublish", "robot": b[0], "sid": str(gone_sid)}
    )
    lab.client(b[0]).unpublish(str(gone_sid))
    fleet.signal_peers(b[0], signal.SIGUSR2)
    time.sleep(max(0.0, tp + timing.partition - time.time()))
    tm = time.time()
    lab.merge()
    time.sleep(timing.after_merge)
    heal: dict[str, Any] = {}
    for system in fleet.systems:
        ev = fleet.events(system)
        truth = {r: own_services(ev, r, tm + timing.after_merge) for r in alive}
        heal[system] = {
            "halves_dropped_each_other_s": first_time(ev, tp, tm, halves_apart(a, b)),
            "all_lists_right_after_merge_s": first_time(
                ev, tm, tm + timing.after_merge, everyone_lists(alive, truth, exact=True)
            ),
        }
    out["partition"] = {"halves": [a, b], **heal}
    return out


def churn_traffic(
    fleet: Fleet, macs: dict[str, str], window: tuple[float, float]
) -> dict[str, Any]:
    """Each system's bytes per robot in `window` (the churn), from the robots' pcaps: UDP or TCP
    payload and whole frames, and datagrams (segments) sent per second."""
    seconds = window[1] - window[0]
    flows = {"sdfr": SDFR_FLOWS, **{p.name: p.flows for p in fleet.peers}}
    per: dict[str, dict[str, Any]] = {s: {} for s in flows}
    for r in fleet.names:
        pcap = fleet.folder / f"{r}.pcap"
        got = ip_traffic(pcap, macs[r], [f for fs in flows.values() for f in fs], window)
        for system, fs in flows.items():
            sums = {
                (d, k): sum(getattr(getattr(got[f], d), k) for f in fs)
                for d in ("tx", "rx")
                for k in ("payload_bytes", "frame_bytes", "datagrams")
            }
            per[system][r] = {
                **{f"{d}_{k}": round(per_5_min(sums[(d, f"{k}_bytes")], seconds) / 1000, 2)
                   for d in ("tx", "rx") for k in ("payload", "frame")},
                "tx_datagrams_per_s": round(sums[("tx", "datagrams")] / seconds, 3),
            }  # fmt: skip
    out: dict[str, Any] = {
        "window_s": round(seconds, 1),
        "flows": {s: [f"{proto} {port}" for proto, port in fs] for s, fs in flows.items()},
        "per_5_min_kB": {
            system: {
                key: spread(v[key] for v in per[system].values())
                for key in ("tx_payload", "rx_payload", "tx_frame", "rx_frame")
            }
            for system in flows
        },
        "tx_datagrams_per_s": {
            system: spread(v["tx_datagrams_per_s"] for v in per[system].values())
            for system in flows
        },
        "per_robot": per,
    }
    if "zeroconf" in flows:
        messages = {
            r: mdns_messages(fleet.folder / f"{r}.pcap", macs[r], window) for r in per["zeroconf"]
        }
        out["zeroconf_sent_per_robot_per_5_min"] = {
            key: round(per_5_min(sum(m[key] for m in messages.values()) / len(messages), seconds))
            for key in ("queries", "responses", "response_bytes")
        }
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument(
        "--quick", action="store_true", help=f"{QUICK.robots} robots, {QUICK.churn:g} s of churn"
    )
    p.add_argument(
        "--smoke",
        action="store_true",
        help="CI's timing: every step for seconds, at a 1 s beacon (numbers mean nothing)",
    )
    p.add_argument(
        "--robots",
        type=numbers(int),
        help="robots, or several sizes run one after the other: 6,20 (default: the timing's)",
    )
    p.add_argument("--churn", type=float, help="seconds of churn (default: the timing's)")
    p.add_argument("--loss", type=numbers(float), default=[0.0],
                   help="loss in %% on every pair of robots, both ways, or several: 0,10 "
                        "(default: 0, a clean medium)")  # fmt: skip
    p.add_argument("--peers", default=",".join(DEFAULT_PEERS),
                   help=f"the systems beside SDfR, comma-separated, of {', '.join(PEERS)} "
                        f"(default: %(default)s)")  # fmt: skip
    paper_lab.run_folder_options(p)
    args = p.parse_args(argv)
    if not paper_lab.has_root("side-by-side"):
        return 2
    base = SMOKE if args.smoke else QUICK if args.quick else FULL
    if args.churn is not None:
        base = dataclasses.replace(base, churn=args.churn)
    try:
        losses = [check_loss(x) for x in args.loss]
        peers = [p.name for p in chosen([n for n in args.peers.split(",") if n])]
    except ValueError as exc:
        err(f"side-by-side: {exc}")
        return 2
    sizes = args.robots or [base.robots]
    if min(sizes) < 4:
        err(f"side-by-side: --robots {min(sizes)}: every step needs at least 4 robots")
        return 2
    top = Path(args.runs).absolute() / f"side-by-side-{datetime.now():%Y%m%d-%H%M%S}"
    results, lines = [], []
    for n, loss in itertools.product(sizes, losses):
        timing = dataclasses.replace(base, robots=n, loss=loss)
        folder = top / f"{n}-robots-loss-{loss:g}"
        result = run(folder, timing, seed=args.seed, peers=peers)
        results.append(result)
        (folder / "side-by-side.json").write_text(json.dumps(result, indent=2) + "\n")
        (folder / "side-by-side.md").write_text("\n".join(markdown(result)) + "\n")
        lines += [*markdown(result), ""]
        print("\n".join(markdown(result)) + "\n", flush=True)
    out: dict[str, Any] = {"runs": results}
    if len(sizes) > 1:
        out["figure"] = str(growth_figure(results, top / "peers-bytes.png"))
    text = json.dumps(out, indent=2) + "\n"
    (top / "side-by-side.json").write_text(text)
    (top / "side-by-side.md").write_text("\n".join(lines))
    if args.out:
        args.out.write_text(text)
    err(f"side-by-side: {top}")
    return 0


def numbers(kind: type[float] | type[int]) -> Any:
    """An argparse type: comma-separated numbers of `kind`."""

    def parse(text: str) -> list[Any]:
        try:
            return [kind(x) for x in text.split(",") if x.strip()]
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{text!r}: not a comma-separated list of {kind.__name__}s"
            ) from None

    return parse


if __name__ == "__main__":
    raise SystemExit(main())
