"""SDfR beside python-zeroconf (mDNS / DNS-SD), on one lab, under one load, in one run.

Every robot runs both: sdfrd at the product's defaults (10 s beacon) with its services
published through the REST API, and a python-zeroconf node (`bench.zc_node`) that registers
the same services and browses the others'.  Both churn the same way (`bench.paper_load`'s
reading of the paper: 70 publishers, one unpublish every 0-5 s, each publisher publishing
again 10 s later), and each robot has a watcher per system that notes when a service of
another robot is listed and when it is not any more (SDfR: `GET /neighbors` every 50 ms;
python-zeroconf: its browser's callbacks, a service counting once resolved, SRV and TXT).
Both act at the same instants, and the same pcaps hold both systems' datagrams (UDP 1900 and
5353), so every figure is measured like for like.

The steps, timed for both systems from the moment they were asked:

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
   expires, 75 minutes by default);
6. a 40 s partition of the robots left into two halves, during which r1 publishes a service
   and a robot of the other half unpublishes one: whether and when each half stopped listing
   the other, and after the merge until every list is right again.

`make bench-paper` runs it after the paper's runs; `python -m bench.side_by_side` runs it alone.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from bench import err, paper_lab
from bench.paper_lab import ROOT, SDFR_PORT, Sampler, captured, conditions, keep_logs
from bench.paper_measure import (
    dig,
    mdns_messages,
    per_5_min,
    propagation,
    read_events,
    spread,
    udp_traffic,
)
from netlab import naming
from netlab.lab import Lab

MDNS_PORT = 5353
PUBLISHERS = 70
SYSTEMS = ("sdfr", "zeroconf")


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


FULL = Timing()
QUICK = Timing(robots=4, churn=30.0, kill_cap=40.0)
#: Every step for seconds, at a 1 s beacon, so that CI runs all of it (`make test`): its
#: numbers mean nothing.
SMOKE = Timing(
    robots=4, beacon=1.0, settle=12.0, churn=8.0, look=4.0, kill_cap=8.0, partition=6.0,
    after_merge=8.0,
)  # fmt: skip

Listed = dict[str, set[tuple[str, str]]]


def replay(events: Iterable[dict[str, Any]], until: float) -> Listed:
    """What each watcher listed at `until`, from its seen/gone events."""
    listed: Listed = {}
    for e in events:
        if float(e["t"]) > until:
            break
        if e["op"] in ("seen", "gone"):
            s = listed.setdefault(str(e["at"]), set())
            item = (str(e["robot"]), str(e["sid"]))
            (s.add if e["op"] == "seen" else s.discard)(item)
    return listed


def first_time(
    events: Sequence[dict[str, Any]],
    since: float,
    until: float,
    holds: Callable[[Listed], bool],
) -> float | None:
    """Seconds from `since` until `holds(listed)` first holds (None: not before `until`)."""
    listed: Listed = {}
    checked = False
    for e in events:
        t = float(e["t"])
        if t > until:
            break
        if t >= since and not checked:
            checked = True
            if holds(listed):
                return 0.0
        if e["op"] in ("seen", "gone"):
            s = listed.setdefault(str(e["at"]), set())
            item = (str(e["robot"]), str(e["sid"]))
            (s.add if e["op"] == "seen" else s.discard)(item)
            if t >= since and holds(listed):
                return round(t - since, 3)
    if not checked and holds(listed):
        return 0.0
    return None


class Fleet:
    """Both systems on one lab: their processes, event files and what they published."""

    def __init__(self, lab: Lab, folder: Path, names: Sequence[str], seed: int) -> None:
        self.lab = lab
        self.folder = folder
        self.names = list(names)
        self.seed = seed
        self.zc: dict[str, subprocess.Popen[bytes]] = {}
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

    def start_zeroconf(self, start_at: float, churn: tuple[float, float]) -> None:
        for name in self.names:
            argv = [
                sys.executable, "-m", "bench.zc_node", "--robot", name,
                "--ip", self.lab.robot(name).ip, "--publishers", str(PUBLISHERS),
                "--start-at", repr(start_at), "--churn-at", repr(churn[0]),
                "--churn-until", repr(churn[1]), "--seed", str(self.seed),
                "--events", str(self.path("zeroconf", "node", name)),
            ]  # fmt: skip
            self.zc[name] = self.lab.popen(
                name, argv, cwd=str(ROOT), stdout=subprocess.DEVNULL, stderr=self._log(name)
            )

    def _log(self, name: str) -> Any:
        return open(self.folder / f"zeroconf-{name}.log", "ab")

    def start_sdfr_load(self, churn: tuple[float, float]) -> None:
        for name in self.names:
            common = [sys.executable, "-m", "bench.paper_load", "--robot", name, "--consumers", "0"]
            self.watchers[name] = self.lab.popen(
                name,
                [*common, "--publishers", "0", "--duration", "86400",
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
        for proc in [*self.watchers.values(), *self.zc.values(), *self.loaders.values()]:
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(proc.pid, signal.SIGTERM)
        for proc in [*self.watchers.values(), *self.zc.values(), *self.loaders.values()]:
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(proc.pid, signal.SIGKILL)
                proc.wait()


def own_services(events: Sequence[dict[str, Any]], robot: str, until: float) -> set[str]:
    """The services `robot` had published at `until`, by its publish/unpublish notes."""
    up: set[str] = set()
    for e in events:
        if float(e["t"]) > until:
            break
        if e.get("robot") == robot and e["op"] == "publish":
            up.add(str(e["sid"]))
        elif e.get("robot") == robot and e["op"] == "unpublish":
            up.discard(str(e["sid"]))
    return up


def everyone_lists(
    watchers: Sequence[str], wanted: dict[str, set[str]], exact: bool = False
) -> Callable[[Listed], bool]:
    """Every watcher lists every wanted (robot, sid) of the other robots (`exact`: and
    nothing else)."""

    def holds(listed: Listed) -> bool:
        for w in watchers:
            want = {(r, s) for r, sids in wanted.items() if r != w for s in sids}
            have = listed.get(w, set())
            if (have != want) if exact else not want <= have:
                return False
        return True

    return holds


def everyone_lists_one(
    watchers: Sequence[str], robot: str, prefixes: tuple[str, ...]
) -> Callable[[Listed], bool]:
    """Every watcher lists a service of `robot` whose id starts with one of `prefixes`."""

    def holds(listed: Listed) -> bool:
        return all(
            any(r == robot and sid.startswith(prefixes) for r, sid in listed.get(w, set()))
            for w in watchers
        )

    return holds


def nobody_lists_these(
    watchers: Sequence[str], robot: str, sids: set[str]
) -> Callable[[Listed], bool]:
    """No watcher lists any of these services of `robot`."""

    def holds(listed: Listed) -> bool:
        return all(
            not (r == robot and s in sids) for w in watchers for r, s in listed.get(w, set())
        )

    return holds


def nobody_lists(watchers: Sequence[str], robots: Sequence[str]) -> Callable[[Listed], bool]:
    def holds(listed: Listed) -> bool:
        return all(r not in robots for w in watchers for r, _ in listed.get(w, set()))

    return holds


def halves_apart(a: Sequence[str], b: Sequence[str]) -> Callable[[Listed], bool]:
    def holds(listed: Listed) -> bool:
        return nobody_lists(a, b)(listed) and nobody_lists(b, a)(listed)

    return holds


def run(folder: Path, timing: Timing = FULL, *, seed: int = 1) -> dict[str, Any]:
    """The side-by-side run; its result (with `table`, the docs' table)."""
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
        "conditions_before": conditions(),
        "problems": [],
    }
    lab_name = naming.unique_lab_name("z")
    err(f"bench-paper: side-by-side: lab {lab_name}, {n} robots, SDfR and python-zeroconf")
    with Lab(lab_name, seed=seed) as lab:
        lab.add_robots(names, {r: (2.0 + i, 5.0) for i, r in enumerate(names)})
        fleet = Fleet(lab, folder, names, seed)
        try:
            with captured(lab, folder, f"udp port {SDFR_PORT} or udp port {MDNS_PORT}"):
                result.update(steps(lab, fleet, names, timing))
        finally:
            fleet.stop_all()
            keep_logs(lab, folder)
    result["conditions_after"] = conditions()
    result["table"] = table(result)
    return result


def steps(lab: Lab, fleet: Fleet, names: list[str], timing: Timing) -> dict[str, Any]:
    out: dict[str, Any] = {}
    look, kill_cap = timing.look, timing.kill_cap
    # 1. start-up, both at once.
    t0 = time.time()
    churn = (t0 + timing.settle, t0 + timing.settle + timing.churn)
    fleet.start_zeroconf(t0 + 0.5, churn)
    lab.start_all(beacon_interval=timing.beacon)
    fleet.start_sdfr_load(churn)
    time.sleep(max(0.0, churn[0] - time.time()))
    startup: dict[str, Any] = {}
    for system in SYSTEMS:
        ev = fleet.events(system)
        initial = {r: own_services(ev, r, churn[0]) for r in names}
        startup[system] = first_time(ev, t0, churn[0], everyone_lists(names, initial))
    out["startup_s"] = startup
    # 2. churn: resources and bytes.
    roots = {f"sdfr-{r}": pid for r in names if (pid := lab.daemon_pid(r)) is not None}
    roots |= {f"zeroconf-{r}": p.pid for r, p in fleet.zc.items()}
    sampler = Sampler(roots)
    sampler.start()
    time.sleep(max(0.0, churn[1] - time.time()))
    sampler.stop()
    use = sampler.result()
    out["resources"] = {
        system: {
            "per_robot": {r: use.get(f"{system}-{r}", {}) for r in names},
            "cpu_percent": spread(use.get(f"{system}-{r}", {}).get("cpu_percent") for r in names),
            "pss_mib": spread(use.get(f"{system}-{r}", {}).get("pss_mib_max") for r in names),
        }
        for system in SYSTEMS
    }
    time.sleep(12.0)  # republishes of the last seconds of churn, and their announcements
    macs = {r: lab.robot(r).mac for r in names}
    out["traffic"] = churn_traffic(fleet.folder, names, macs, churn)
    out["seen_by_peers"] = {
        system: propagation(
            fleet.events(system), names, since=churn[0], until=churn[1], start="asked"
        )
        for system in SYSTEMS
    }
    # 3. a new service on r1.
    t = time.time()
    fleet.extra_events.append({"t": t, "op": "publish", "robot": "r1", "sid": "extra1"})
    lab.client("r1").publish("extra", "bench.extra", service_id="extra1")
    os.kill(fleet.zc["r1"].pid, signal.SIGUSR1)
    time.sleep(look)
    others = names[1:]
    out["new_service_s"] = {
        system: first_time(
            fleet.events(system),
            t,
            t + look,
            everyone_lists_one(others, "r1", ("extra1", "p1001x")),
        )
        for system in SYSTEMS
    }
    # 4. a graceful leave of the last robot: its services at the leave; apart, what the others
    # still list of those it had unpublished before.
    leaver, victim = names[-1], names[-2]
    left = names[:-1]
    t = time.time()
    lab.stop(leaver)
    os.kill(fleet.zc[leaver].pid, signal.SIGTERM)
    time.sleep(look)
    out["graceful_leave_s"], out["stale_after_leave"] = {}, {}
    for system in SYSTEMS:
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
    os.kill(fleet.zc[victim].pid, signal.SIGKILL)
    end = t + kill_cap
    while time.time() < end:
        done = [first_time(fleet.events(s), t, end, nobody_lists(alive, [victim])) for s in SYSTEMS]
        if all(d is not None for d in done):
            break
        time.sleep(2.0)
    out["kill_9_s"] = {
        system: first_time(fleet.events(system), t, end, nobody_lists(alive, [victim]))
        for system in SYSTEMS
    }
    # 6. a 40 s partition of the rest into two halves, with a change on each side.
    half = len(alive) // 2
    a, b = alive[:half], alive[half:]
    tp = time.time()
    lab.partition([a, b])
    time.sleep(min(5.0, timing.partition / 4))
    fleet.extra_events.append({"t": time.time(), "op": "publish", "robot": a[0], "sid": "apart1"})
    lab.client(a[0]).publish("apart", "bench.extra", service_id="apart1")
    os.kill(fleet.zc[a[0]].pid, signal.SIGUSR1)
    gone_sid = next(s["id"] for s in lab.client(b[0]).services())
    fleet.extra_events.append(
        {"t": time.time(), "op": "unpublish", "robot": b[0], "sid": str(gone_sid)}
    )
    lab.client(b[0]).unpublish(str(gone_sid))
    os.kill(fleet.zc[b[0]].pid, signal.SIGUSR2)
    time.sleep(max(0.0, tp + timing.partition - time.time()))
    tm = time.time()
    lab.merge()
    time.sleep(timing.after_merge)
    heal: dict[str, Any] = {}
    for system in SYSTEMS:
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
    folder: Path, names: Sequence[str], macs: dict[str, str], window: tuple[float, float]
) -> dict[str, Any]:
    seconds = window[1] - window[0]
    per: dict[str, dict[str, Any]] = {s: {} for s in SYSTEMS}
    for r in names:
        t = udp_traffic(folder / f"{r}.pcap", macs[r], [SDFR_PORT, MDNS_PORT], window)
        for system, port in (("sdfr", SDFR_PORT), ("zeroconf", MDNS_PORT)):
            flows = t[port]
            per[system][r] = {
                f"{d}_{s}": round(
                    per_5_min(getattr(getattr(flows, d), f"{s}_bytes"), seconds) / 1000, 2
                )
                for d in ("tx", "rx")
                for s in ("payload", "frame")
            }
    messages = {r: mdns_messages(folder / f"{r}.pcap", macs[r], window) for r in names}
    return {
        "window_s": round(seconds, 1),
        "zeroconf_sent_per_robot_per_5_min": {
            key: round(per_5_min(sum(m[key] for m in messages.values()) / len(names), seconds))
            for key in ("queries", "responses", "response_bytes")
        },
        "per_5_min_kB": {
            system: {
                key: spread(v[key] for v in per[system].values())
                for key in ("tx_payload", "rx_payload", "tx_frame", "rx_frame")
            }
            for system in SYSTEMS
        },
        "per_robot": per,
    }


def _fmt(v: Any, unit: str = " s") -> str:
    return "not seen" if v is None else f"{v:.2f}{unit}" if isinstance(v, float) else str(v)


def table(r: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per measure: SDfR, python-zeroconf and their ratio (zeroconf / SDfR)."""
    rows: list[dict[str, Any]] = []

    def row(measure: str, sdfr: Any, zc: Any, note: str = "") -> None:
        ratio = (
            round(zc / sdfr, 2)
            if isinstance(sdfr, int | float) and isinstance(zc, int | float) and sdfr
            else None
        )
        rows.append({"measure": measure, "sdfr": sdfr, "zeroconf": zc, "ratio": ratio,
                     "note": note})  # fmt: skip

    def both(key: str) -> tuple[Any, Any]:
        v = r.get(key, {})
        return v.get("sdfr"), v.get("zeroconf")

    row("start-up: all robots list all services (s)", *both("startup_s"))
    row("a new service seen on all peers (s)", *both("new_service_s"))
    stale = {s: len(v) for s, v in r.get("stale_after_leave", {}).items()}
    row(
        "a graceful leave seen on all peers (s)",
        *both("graceful_leave_s"),
        "its services at the leave; still listed after it, of those it had unpublished "
        f"before: SDfR {stale.get('sdfr', '?')}, python-zeroconf {stale.get('zeroconf', '?')}",
    )
    row(
        f"a kill -9 seen on all peers (s, waited at most {r['kill_cap_s']:g} s)",
        *both("kill_9_s"),
        "None: not seen within the cap",
    )
    part = r.get("partition", {})
    row(
        f"{r['partition_s']:g} s partition: each half stops listing the other (s)",
        dig(part, "sdfr", "halves_dropped_each_other_s"),
        dig(part, "zeroconf", "halves_dropped_each_other_s"),
        "None: not within the partition",
    )
    row(
        "after the merge, every list right again (s)",
        dig(part, "sdfr", "all_lists_right_after_merge_s"),
        dig(part, "zeroconf", "all_lists_right_after_merge_s"),
        f"None: not within {r['timing_s']['after_merge']:g} s",
    )
    tr = r.get("traffic", {}).get("per_5_min_kB", {})
    for key, label in (("tx_payload", "TX"), ("rx_payload", "RX")):
        row(
            f"{label} kB per robot per 5 min (UDP payload; mean of robots)",
            dig(tr, "sdfr", key, "mean"),
            dig(tr, "zeroconf", key, "mean"),
        )
    for key, label in (("tx_frame", "TX"), ("rx_frame", "RX")):
        row(
            f"{label} kB per robot per 5 min (whole frames)",
            dig(tr, "sdfr", key, "mean"),
            dig(tr, "zeroconf", key, "mean"),
        )
    res = r.get("resources", {})
    row(
        "CPU per robot, % of one core (mean)",
        dig(res, "sdfr", "cpu_percent", "mean"),
        dig(res, "zeroconf", "cpu_percent", "mean"),
        "SDfR: the daemon's 3 processes (API answering the watcher every 50 ms included); "
        "zeroconf: the node's process",
    )
    row(
        "PSS per robot, MiB (mean of the robots' max)",
        dig(res, "sdfr", "pss_mib", "mean"),
        dig(res, "zeroconf", "pss_mib", "mean"),
    )
    seen = r.get("seen_by_peers", {})
    row(
        "churn: a change listed by each peer, p50 / p99 (ms)",
        f"{dig(seen, 'sdfr', 'publish', 'p50_ms')} / {dig(seen, 'sdfr', 'publish', 'p99_ms')}",
        f"{dig(seen, 'zeroconf', 'publish', 'p50_ms')} / "
        f"{dig(seen, 'zeroconf', 'publish', 'p99_ms')}",
        "publishes, from the moment each was asked for",
    )
    return rows


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
    p.add_argument("--robots", type=int, help="robots (default: the timing's)")
    p.add_argument("--churn", type=float, help="seconds of churn (default: the timing's)")
    paper_lab.run_folder_options(p)
    args = p.parse_args(argv)
    if not paper_lab.has_root("side-by-side"):
        return 2
    timing = SMOKE if args.smoke else QUICK if args.quick else FULL
    if args.robots is not None:
        timing = dataclasses.replace(timing, robots=args.robots)
    if args.churn is not None:
        timing = dataclasses.replace(timing, churn=args.churn)
    folder = Path(args.runs).absolute() / f"side-by-side-{datetime.now():%Y%m%d-%H%M%S}"
    result = run(folder, timing, seed=args.seed)
    text = json.dumps(result, indent=2) + "\n"
    (folder / "side-by-side.json").write_text(text)
    if args.out:
        args.out.write_text(text)
    for row in result["table"]:
        sdfr, zc = _fmt(row["sdfr"], ""), _fmt(row["zeroconf"], "")
        note = f" ({row['note']})" if row["note"] else ""
        print(f"{row['measure']}: SDfR {sdfr}, python-zeroconf {zc}{note}")
    err(f"side-by-side: {folder}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
