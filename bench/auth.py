"""What authenticated datagrams and the proofs of freshness cost: bytes, CPU and join time.

Four measures, each signed and unsigned (open and keyed) side by side in the same run:

1. bytes: every kind of datagram a robot sends (search, ping, compact reply, beacon, a
   one-service delta, a full Update part, Byebye), encoded as the daemon encodes them, then
   sealed with a counter of the size a robot reaches in a day (6 digits), for the fleet or for
   one robot as the daemon seals it;
2. CPU: microseconds per datagram to seal and to check a seal (sdfr.auth), and for the whole
   receive path of the protocol core (seal check, decode, freshness, bookkeeping) fed a
   stream of beacons and pings of a peer it has proven (in a two-robot simulator run);
   medians of repeated timed loops;
3. a fleet: 6 robots with 100 services each, 5 minutes of virtual time at the product's 10 s
   beacon (the protocol core on an in-memory medium, sdfr.testing.simnet), bytes each robot
   sent and received (UDP payload), open and keyed;
4. dynamics: the same fleet (6 robots, 100 services, CoreConfig defaults), open and keyed,
   over several seeds and at two link delays (1-4 ms and 20-50 ms one way): how long a new
   robot takes to join (from its start until every other robot lists it with its whole set and
   it lists every other robot with theirs), a robot restarted (gracefully, and killed and back
   5 s later) until it is listed again everywhere at its new boot; and the bytes on the air per
   robot per minute in an idle fleet and in a churning one (a service change every 10 s on
   one robot after the other), with how long each change takes to be listed everywhere.

`--baseline REV|DIR` runs the same bench code against another sdfr package (a git revision,
extracted with `git archive`, or a checkout such as a `git worktree`) in a child process, and
adds its figures and a side-by-side table (baseline vs this checkout) to the JSON.

JSON on stdout and in --out (runs/bench-auth.json); a table on stderr.
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import platform
import random
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Iterator
from datetime import datetime
from functools import partial
from pathlib import Path
from typing import Any

import sdfr
from sdfr import auth, wire
from sdfr.auth import Keyring, Sealed
from sdfr.model import Service, service_digest
from sdfr.testing.simnet import SimNet, kind_of
from sdfr.wire import Alive, Byebye, Discovery, Origin, Reject, Response, Update

ROOT = Path(__file__).resolve().parent.parent
KEY = bytes(range(32))
COUNTER = 123_456  # six digits: a robot's counter after about a day of a small fleet
FIVE_MINUTES_S = 300.0
STARTUP_S = 30.0
#: Seals that name their recipient and the sender's address (seals v2, f0bc644); before,
#: `auth.seal(data, key, counter)` and `auth.check(data, keyring)` took nothing else.
BOUND_SEALS = "to" in inspect.signature(auth.seal).parameters
#: Pings and beacons carry 64-bit random nonces since f0bc644 (before: a 30-bit random start,
#: counting up): a typical sequence number of each, for the datagram sizes.
SEQ = 11_400_714_819_323_198_485 if wire.MAX_SEQ > 2**53 else 1_034_567_890
#: What a datagram costs below its UDP payload on an Ethernet link (Ethernet II, IPv4, UDP).
FRAME_OVERHEAD = 14 + 20 + 8

#: The dynamics: fleet size, services per robot, link delays (one way, uniform), how long a
#: robot restarted after a kill stays down, the service change period of the churning fleet.
DYN_ROBOTS = 6
DYN_SERVICES = 100
DELAYS: dict[str, tuple[float, float]] = {"1-4 ms": (0.001, 0.004), "20-50 ms": (0.020, 0.050)}
DOWN_S = 5.0
CHURN_EVERY_S = 10.0
#: Give up waiting for a join (or a change to be seen) after this long: counted as not joined.
JOIN_TIMEOUT_S = 120.0


def seal(data: bytes, counter: int, *, to: str | None = None, sender: str = "") -> bytes:
    """`auth.seal` with KEY, bound to recipient and sender where the seals say them."""
    if BOUND_SEALS:
        return auth.seal(data, KEY, counter, to=to, sender=sender)
    return auth.seal(data, KEY, counter)


def check(data: bytes, ring: Keyring, *, me: str = "", src: str = "") -> Sealed | Reject | None:
    if BOUND_SEALS:
        return auth.check(data, ring, me=me, src=src)
    return auth.check(data, ring)


def services(robot: str, n: int) -> list[Service]:
    return [
        Service(
            id=f"{robot}-{i:03d}",
            name=f"{robot} service {i}",
            type=f"sensor.kind{i % 7}",
            url=f"http://{robot}.local:9000/s{i}",
            attributes={"fps": 30, "frame": f"{robot}/base_link"},
        )
        for i in range(n)
    ]


#: Kinds of datagram sent to one robot (sealed for it), the rest to the fleet.
UNICAST_KINDS = frozenset(
    {
        "ping (unicast Discovery)",
        "ping reply (compact Response)",
        "ping reply carrying a ping",
        "ping reply (compact form)",
    }
)


def datagram_kinds() -> dict[str, bytes]:
    """One datagram of each kind, unsigned, as robot r1 of fleet 1 sends it."""
    svcs = services("r1", 100)
    origin = Origin(1, "r1", 219_000_000, 42, service_digest(svcs))
    compact = Origin(1, "r1", 219_000_000, 42, service_digest(svcs), wire.WIRE_COMPACT)
    location = "http://10.1.0.1:8701/description.json"
    peer = ("10.1.0.2", 1900)
    parts = wire.encode_update_parts(origin, location, 30, svcs)
    delta = Update(origin, location, 30, 0, 1, (svcs[0],), base=41, removed=())
    return {
        "search (multicast Discovery)": wire.encode(
            Discovery(origin, wire.fleet_target(1), 1, want=wire.WANT_ALL)
        ),
        "ping (unicast Discovery)": wire.encode(
            Discovery(origin, "uuid:r2", 0, seq=SEQ, multicast=False),
            group=peer[0],
            port=peer[1],
        ),
        "ping reply (compact Response)": wire.encode(Response(origin, "uuid:r1", "", 0, SEQ)),
        "ping reply carrying a ping": wire.encode(Response(origin, "uuid:r1", "", 0, SEQ, SEQ + 1)),
        "ping reply (compact form)": wire.encode(
            Response(compact, "uuid:r1", "", 0, SEQ), compact=True
        ),
        "beacon (Alive)": wire.encode(Alive(origin, location, 30)),
        "beacon that pings (compact Alive)": wire.encode(
            Alive(compact, "", 0, SEQ, 1), compact=True
        ),
        "one-service delta (Update)": wire.encode(delta),
        "full Update part": max(parts, key=len),
        "Byebye": wire.encode(Byebye(origin)),
    }


def sealed_kind(kind: str, data: bytes, counter: int = COUNTER) -> bytes:
    to = "r2" if kind in UNICAST_KINDS else None
    return seal(data, counter, to=to, sender="10.1.0.1")


def bytes_per_datagram() -> dict[str, dict[str, float]]:
    out = {}
    for kind, data in datagram_kinds().items():
        sealed = sealed_kind(kind, data)
        assert len(sealed) <= wire.MAX_DATAGRAM
        out[kind] = {
            "unsigned": len(data),
            "signed": len(sealed),
            "overhead": len(sealed) - len(data),
            "overhead_pct": round(100 * (len(sealed) - len(data)) / len(data), 1),
        }
    return out


def update_parts() -> dict[str, int]:
    """How many Update parts a whole set of 100 services takes (the codec leaves
    `wire.SEAL_RESERVE` bytes of each free for a seal)."""
    svcs = services("r1", 100)
    origin = Origin(1, "r1", 219_000_000, 42, service_digest(svcs))
    parts = wire.encode_update_parts(origin, "http://10.1.0.1:8701/description.json", 30, svcs)
    return {
        "seal_reserve": wire.SEAL_RESERVE,
        "parts_for_100_services": len(parts),
        "bytes_for_100_services": sum(len(p) for p in parts),
    }


def per_call_us(fn: Callable[[], object], n: int, repeats: int) -> float:
    """Median over `repeats` timed loops of `n` calls, in microseconds per call."""
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        samples.append((time.perf_counter() - t0) / n * 1e6)
    return round(statistics.median(samples), 3)


def seal_and_check_cpu(n: int, repeats: int) -> dict[str, dict[str, float]]:
    kinds = datagram_kinds()
    ring = Keyring.of([KEY])
    out = {}
    for label, kind in (
        ("ping (small)", "ping (unicast Discovery)"),
        ("full Update part", "full Update part"),
    ):
        data = kinds[kind]
        to = "r2" if kind in UNICAST_KINDS else None
        sealed = sealed_kind(kind, data)
        assert isinstance(check(sealed, ring, me="r2", src="10.1.0.1"), Sealed)
        out[label] = {
            "bytes": len(data),
            "seal_us": per_call_us(
                partial(seal, data, COUNTER, to=to, sender="10.1.0.1"), n, repeats
            ),
            "check_us": per_call_us(
                partial(check, sealed, ring, me="r2", src="10.1.0.1"), n, repeats
            ),
            "check_unsigned_us": per_call_us(
                partial(check, data, ring, me="r2", src="10.1.0.1"), n, repeats
            ),
        }
    return out


def receive_cpu(n: int, repeats: int) -> dict[str, float]:
    """µs per datagram through Core.receive: beacons and pings of a peer it has proven.

    r1 and r2 meet in the simulator first (r1 challenges r2, r2 answers: r2 is listed by r1,
    by either core's rules); then r1's core alone is fed a stream of r2's beacons and pings,
    4 ms apart (under the per-source limit, and within r2's proof window)."""
    out: dict[str, float] = {}
    for label, ring in (("unsigned", auth.OPEN), ("signed", Keyring.of([KEY]))):
        samples = []
        for r in range(repeats):
            net = SimNet(seed=r + 1)
            net.add("r1", services=services("r1", 10), keyring=ring)
            net.add("r2", services=services("r2", 10), keyring=ring)
            net.run_for(15.0)
            assert net.all_see_all(["r1", "r2"]), "r1 and r2 did not meet"
            core, peer = net.nodes["r1"].core, net.nodes["r2"].core
            src = net.nodes["r2"].addr
            origin = peer._origin()
            stream = [
                (wire.encode(Alive(origin, peer.location, 30)), None),
                (
                    wire.encode(
                        Discovery(origin, "uuid:r1", 0, seq=77, multicast=False),
                        group=net.nodes["r1"].addr[0],
                        port=1900,
                    ),
                    "r1",
                ),
            ]
            first = peer._sent_seals + 1
            datagrams = [
                seal(stream[i % 2][0], first + i, to=stream[i % 2][1], sender=src[0])
                if ring.keyed
                else stream[i % 2][0]
                for i in range(n)
            ]
            core.datagrams_to_send()
            rejects = Counter(core.counters.rejects)
            t_start = net.now
            t0 = time.perf_counter()
            for i, data in enumerate(datagrams):
                core.receive(data, src, t_start + i * 4e-3)
                core.datagrams_to_send()
            samples.append((time.perf_counter() - t0) / n * 1e6)
            assert core.counters.rejects == rejects, core.counters.rejects - rejects
            assert "r2" in core.reachable()
        out[f"{label}_us"] = round(statistics.median(samples), 3)
    out["overhead_us"] = round(out["signed_us"] - out["unsigned_us"], 3)
    return out


def fleet_bytes(robots: int, n_services: int, seconds: float) -> dict[str, object]:
    """Per robot, bytes sent and received, open and keyed: during the start-up (the first
    STARTUP_S, everyone fetching everyone's set), then in `seconds` of steady state scaled to
    5 minutes.  Virtual time, so the numbers are exact and the run takes a second."""
    out: dict[str, Any] = {}
    for label, ring in (("open", auth.OPEN), ("keyed", Keyring.of([KEY]))):
        net = SimNet(seed=7)
        names = [f"r{i}" for i in range(1, robots + 1)]
        for name in names:
            net.add(name, services=services(name, n_services), keyring=ring)
        net.run_for(STARTUP_S)
        assert net.all_see_all(names)
        cores = [net.nodes[n].core for n in names]
        start = [(c.counters.bytes_out, c.counters.bytes_in) for c in cores]
        net.run_for(seconds)
        assert net.all_see_all(names)
        scale = FIVE_MINUTES_S / seconds
        out[label] = {
            "startup_tx_kb_per_robot": round(statistics.mean(s[0] for s in start) / 1000, 1),
            "startup_rx_kb_per_robot": round(statistics.mean(s[1] for s in start) / 1000, 1),
            "tx_kb_per_robot_5min": round(
                statistics.mean(
                    (c.counters.bytes_out - s[0]) * scale / 1000
                    for c, s in zip(cores, start, strict=True)
                ),
                1,
            ),
            "rx_kb_per_robot_5min": round(
                statistics.mean(
                    (c.counters.bytes_in - s[1]) * scale / 1000
                    for c, s in zip(cores, start, strict=True)
                ),
                1,
            ),
        }
    open_, keyed = out["open"], out["keyed"]
    for key in ("tx_kb_per_robot_5min", "rx_kb_per_robot_5min"):
        out[key.split("_")[0] + "_overhead_pct"] = round(100 * (keyed[key] / open_[key] - 1), 1)
    out["conditions"] = (
        f"{robots} robots, {n_services} services each, no churn, the 10 s beacon; steady state "
        f"over {seconds:.0f} s of virtual time after a {STARTUP_S:.0f} s start-up, scaled to 5 "
        "minutes (protocol core on an in-memory medium, no loss); UDP payload"
    )
    return out


# -- dynamics: join, restart, idle and churning fleets -------------------------------------


def rings() -> Iterator[tuple[str, Keyring]]:
    yield "open", auth.OPEN
    yield "keyed", Keyring.of([KEY])


def listed(net: SimNet, a: str, b: str) -> bool:
    """Robot `a` lists robot `b` (reachable and proven: what its /neighbors shows) at `b`'s
    current boot, with `b`'s whole current set."""
    peer = net.nodes[a].core.peers.get(b)
    other = net.nodes[b].core
    return (
        peer is not None
        and peer.reachable
        and peer.proven
        and peer.boot_id == other.boot_id
        and peer.services == other.services
    )


def watch(
    net: SimNet, preds: dict[str, Callable[[], bool]], timeout: float
) -> dict[str, float | None]:
    """Run until every predicate held once (checked after every event of the medium), or
    `timeout` s; when each first held, in seconds from now (None: not within the timeout)."""
    t0 = net.now
    seen: dict[str, float | None] = {k: (0.0 if p() else None) for k, p in preds.items()}

    def check() -> None:
        for k, p in preds.items():
            if seen[k] is None and p():
                seen[k] = net.now - t0

    net.after_event = check
    try:
        while any(v is None for v in seen.values()) and net.now < t0 + timeout:
            net.run_until(min(net.now + 1.0, t0 + timeout))
    finally:
        net.after_event = None
    return seen


def comes_in(net: SimNet, name: str, timeout: float) -> dict[str, float | None]:
    """Watch robot `name` (just started) until the fleet lists it and it lists the fleet."""
    others = [n for n in net.nodes if n != name and net.nodes[n].up]

    def by_all() -> bool:
        return all(listed(net, o, name) for o in others)

    def of_all() -> bool:
        return all(listed(net, name, o) for o in others)

    seen = watch(net, {"listed_by_all": by_all, "lists_all": of_all}, timeout)
    a, b = seen["listed_by_all"], seen["lists_all"]
    seen["both"] = None if a is None or b is None else max(a, b)
    return seen


class Air:
    """What goes on the air (each datagram once, multicast or not) and what reaches each
    robot, through the simulator's observer hooks."""

    def __init__(self, net: SimNet) -> None:
        self.tx = 0
        self.datagrams = 0
        self.rx = 0
        self.kinds: Counter[str] = Counter()

        def sent(node: object, data: bytes, dst: object) -> None:
            self.tx += len(data)
            self.datagrams += 1
            k = kind_of(data)
            self.kinds[k + (" (multicast)" if dst is None else "")] += len(data)

        def received(node: object, data: bytes, src: object) -> None:
            self.rx += len(data)

        net.on_send = sent
        net.on_receive = received

    def mark(self) -> tuple[int, int, int, Counter[str]]:
        return self.tx, self.datagrams, self.rx, Counter(self.kinds)


def per_robot_minute(
    air: Air, mark: tuple[int, int, int, Counter[str]], robots: int, seconds: float
) -> dict[str, Any]:
    tx, dg, rx, kinds = mark
    scale = 60.0 / seconds / robots
    return {
        "tx_bytes": (air.tx - tx) * scale,
        "tx_datagrams": (air.datagrams - dg) * scale,
        "rx_bytes": (air.rx - rx) * scale,
        "tx_bytes_by_kind": {k: v * scale for k, v in (air.kinds - kinds).items()},
    }


def fleet_of(net: SimNet, n: int, ring: Keyring, first: int = 1) -> list[str]:
    names = [f"r{i}" for i in range(first, first + n)]
    for name in names:
        net.add(name, services=services(name, DYN_SERVICES), keyring=ring)
    return names


def history(net: SimNet, name: str) -> list[Any]:
    """The peers robot `name`'s daemon has saved (its history map): those proven once."""
    core = net.nodes[name].core
    return [core.view(p) for p in core.peers.values() if getattr(p, "known", p.proven)]


def reseed(net: SimNet, seed: int, step: int) -> None:
    """The medium's random numbers from here on depend on (seed, step) only: the same draws
    at either link delay (each delay is lo + (hi - lo) * u of the same u), and the same
    random stream for a core created now, so that the two delays' runs pair up."""
    net.rng.seed(seed * 1_000_003 + step)


def join_and_restarts(ring: Keyring, delay: tuple[float, float], seed: int) -> dict[str, Any]:
    """One fleet: r1..r5 settle; r6 joins; later r3 restarts (stop, start at once) and r4 is
    killed and started again DOWN_S later; each start at a random phase of the beacons."""
    net = SimNet(seed=seed, delay=delay)
    phase = random.Random(seed * 7919 + 1)
    names = fleet_of(net, DYN_ROBOTS - 1, ring)
    net.run_for(STARTUP_S + phase.uniform(0, 10))
    assert net.all_see_all(names), "the first robots did not meet"
    air = Air(net)
    mark = air.mark()
    reseed(net, seed, 1)
    net.add(f"r{DYN_ROBOTS}", services=services(f"r{DYN_ROBOTS}", DYN_SERVICES), keyring=ring)
    t_join = net.now
    join = comes_in(net, f"r{DYN_ROBOTS}", JOIN_TIMEOUT_S)
    net.run_until(t_join + 30.0)
    join_air = per_robot_minute(air, mark, DYN_ROBOTS, 30.0)

    names = list(net.nodes)
    net.run_for(30.0 + phase.uniform(0, 10))
    assert net.all_see_all(names), "the fleet did not settle after the join"
    saved = history(net, "r3")
    reseed(net, seed, 2)
    net.restart("r3", boot_id=2, graceful=True, history=saved)
    graceful = comes_in(net, "r3", JOIN_TIMEOUT_S)

    net.run_for(40.0 + phase.uniform(0, 10))
    assert net.all_see_all(names), "the fleet did not settle after the restart"
    saved = history(net, "r4")
    net.kill("r4")
    net.run_for(DOWN_S)
    reseed(net, seed, 3)
    net.restart("r4", boot_id=2, graceful=False, history=saved)
    crash = comes_in(net, "r4", JOIN_TIMEOUT_S)
    return {"join": join, "join_air": join_air, "restart": graceful, "crash_restart": crash}


def idle_and_churn(
    ring: Keyring, delay: tuple[float, float], seed: int, seconds: float
) -> dict[str, Any]:
    """A settled fleet of DYN_ROBOTS: `seconds` idle, then `seconds` with a service change every
    CHURN_EVERY_S on one robot after the other (one service's attributes change: a delta)."""
    net = SimNet(seed=seed, delay=delay)
    names = fleet_of(net, DYN_ROBOTS, ring)
    net.run_for(60.0)
    assert net.all_see_all(names), "the fleet did not settle"
    air = Air(net)
    mark = air.mark()
    net.run_for(seconds)
    idle = per_robot_minute(air, mark, DYN_ROBOTS, seconds)
    assert net.all_see_all(names)

    latencies: list[float | None] = []
    pending: dict[int, tuple[str, tuple[Service, ...], float]] = {}

    def change(k: int) -> None:
        name = names[k % len(names)]
        core = net.nodes[name].core
        svcs = list(core.services)
        first = svcs[0]
        svcs[0] = Service(
            id=first.id,
            name=first.name,
            type=first.type,
            url=first.url,
            attributes={**first.attributes, "fps": 1 + k},
        )
        net.set_services(name, core.version + 1, svcs)
        latencies.append(None)
        pending[len(latencies) - 1] = (name, net.nodes[name].core.services, net.now)

    def seen_everywhere() -> None:
        for i, (name, svcs, t) in list(pending.items()):
            if all(
                (p := net.nodes[o].core.peers.get(name)) is not None and p.services == svcs
                for o in names
                if o != name
            ):
                latencies[i] = net.now - t
                del pending[i]

    reseed(net, seed, 4)
    t0 = net.now
    for k in range(int(seconds // CHURN_EVERY_S)):
        net.call_at(t0 + CHURN_EVERY_S * k + 5.0, partial(change, k))
    mark = air.mark()
    net.after_event = seen_everywhere
    net.run_for(seconds)
    net.after_event = None
    churn = per_robot_minute(air, mark, DYN_ROBOTS, seconds)
    net.run_for(10.0)
    assert net.all_see_all(names), "the churning fleet did not settle"
    return {"idle": idle, "churn": churn, "change_seen_s": latencies}


def stats(values: list[float | None], ndigits: int = 3) -> dict[str, Any]:
    got = sorted(v for v in values if v is not None)
    return {
        "median_s": round(statistics.median(got), ndigits) if got else None,
        "max_s": round(max(got), ndigits) if got else None,
        "min_s": round(min(got), ndigits) if got else None,
        "runs": len(values),
        "not_within_timeout": len(values) - len(got),
    }


def mean_of(rows: list[dict[str, Any]], key: str) -> float:
    return statistics.mean(float(r[key]) for r in rows)


def air_summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    kinds: Counter[str] = Counter()
    for r in rows:
        for k, v in r["tx_bytes_by_kind"].items():
            kinds[k] += v / len(rows)
    tx, dg = mean_of(rows, "tx_bytes"), mean_of(rows, "tx_datagrams")
    return {
        "tx_bytes_per_robot_min": round(tx, 1),
        "tx_datagrams_per_robot_min": round(dg, 2),
        "tx_frame_bytes_per_robot_min": round(tx + FRAME_OVERHEAD * dg, 1),
        "rx_bytes_per_robot_min": round(mean_of(rows, "rx_bytes"), 1),
        "tx_bytes_per_robot_min_by_kind": {k: round(v, 1) for k, v in sorted(kinds.items())},
    }


def delays_on_path(lo: list[float | None], hi: list[float | None]) -> float | None:
    """Median over paired runs (same seed) of (time at 20-50 ms - time at 1-4 ms) divided by
    the difference of the mean one-way delays: how many one-way link delays the path holds
    (a round trip is 2)."""
    (a, b), (c, d) = DELAYS["1-4 ms"], DELAYS["20-50 ms"]
    step = (c + d - a - b) / 2
    pairs = [(y - x) / step for x, y in zip(lo, hi, strict=True) if x is not None and y is not None]
    return round(statistics.median(pairs), 1) if pairs else None


WHATS = ("join", "restart", "crash_restart")


def dynamics(seeds: int, bytes_seeds: int, seconds: float) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for label, ring in rings():
        side: dict[str, Any] = {}
        runs = {
            dl: [join_and_restarts(ring, delay, seed) for seed in range(1, seeds + 1)]
            for dl, delay in DELAYS.items()
        }
        for dl in DELAYS:
            row: dict[str, Any] = {}
            for what in WHATS:
                row[what] = stats([r[what]["both"] for r in runs[dl]])
                for part in ("listed_by_all", "lists_all"):
                    row[what][f"{part}_median_s"] = stats([r[what][part] for r in runs[dl]])[
                        "median_s"
                    ]
            row["join_30s_air"] = air_summary([r["join_air"] for r in runs[dl]])
            side[dl] = row
        side["link_delays_on_the_path"] = {
            what: delays_on_path(
                [r[what]["both"] for r in runs["1-4 ms"]],
                [r[what]["both"] for r in runs["20-50 ms"]],
            )
            for what in WHATS
        }
        churned = {
            dl: [idle_and_churn(ring, delay, s, seconds) for s in range(1, bytes_seeds + 1)]
            for dl, delay in DELAYS.items()
        }
        for dl in DELAYS:
            side[dl]["change_seen"] = stats([x for r in churned[dl] for x in r["change_seen_s"]])
        side["link_delays_on_the_path"]["change_seen"] = delays_on_path(
            [x for r in churned["1-4 ms"] for x in r["change_seen_s"]],
            [x for r in churned["20-50 ms"] for x in r["change_seen_s"]],
        )
        side["idle"] = air_summary([r["idle"] for r in churned["1-4 ms"]])
        side["churn"] = air_summary([r["churn"] for r in churned["1-4 ms"]])
        out[label] = side
    out["conditions"] = (
        f"{DYN_ROBOTS} robots, {DYN_SERVICES} services each, CoreConfig defaults (10 s beacon, "
        "miss limit 3); protocol cores on the in-memory medium of sdfr.testing.simnet in "
        "virtual time, no loss, each link delay uniform in the range named (one way). "
        "join: r1..r5 settle for 30-40 s, then r6 starts; 'both' runs from its start until "
        "every other robot lists it (reachable, proven, at its boot, with its whole set: "
        "listed_by_all) and it lists every other robot so (lists_all), checked after every "
        f"event; median, min and max over {seeds} seeds. restart: r3 stops (Byebye) and starts "
        "at once with boot 2 and its saved history; crash_restart: r4 is killed and starts "
        f"{DOWN_S:.0f} s later with boot 2 and its history; both measured from the new start "
        "until listed everywhere at the new boot with its set, both ways. "
        "link_delays_on_the_path: median over seeds of (time at 20-50 ms - time at 1-4 ms, "
        "same seed and random draws) / 32.5 ms: one-way link delays on the critical path (a "
        "round trip is 2). join_30s_air: what every robot sent in the 30 s after the join "
        f"began, per robot per minute. idle, churn: {bytes_seeds} seeds of {seconds:.0f} s "
        "each after a 60 s settle (1-4 ms link): idle, then a one-service change every 10 s "
        "on r1, r2, ... in turn; tx: UDP payload sent, each datagram once as on the air; "
        f"frame: plus {FRAME_OVERHEAD} bytes a datagram (Ethernet, IPv4, UDP); rx: payload "
        "reaching a robot. change_seen: from a change until every other robot holds the new "
        "set (all changes of the churn runs at that delay)."
    )
    return out


# -- the core measured, and a baseline beside it --------------------------------------------


#: The files whose behaviour this bench measures (the others do not take part in it).
TRUST_CORE = ("sdfr/protocol/", "sdfr/auth.py", "sdfr/wire/", "sdfr/limits.py", "sdfr/model.py")


def core_identity() -> dict[str, Any]:
    """Which sdfr was measured: its files, the git revision of the tree they are in, and
    whether the trust core's files differ from it."""
    package = Path(sdfr.__file__).resolve().parent
    out: dict[str, Any] = {"sdfr": str(package / "__init__.py")}
    stamp = package.parent / ".bench-revision"
    if stamp.exists():
        out["git"] = stamp.read_text().strip()
        out["modified"] = out["trust_core_modified"] = []
        return out

    def git(*args: str) -> str:
        res = subprocess.run(
            ["git", "-C", str(package.parent), *args], capture_output=True, text=True
        )
        return res.stdout.rstrip() if res.returncode == 0 else ""

    out["git"] = git("describe", "--always", "--tags") or "unknown"
    out["modified"] = [
        line[3:] for line in git("status", "--porcelain", "--", "sdfr").splitlines() if line
    ]
    out["trust_core_modified"] = [m for m in out["modified"] if m.startswith(TRUST_CORE)]
    return out


#: Run in the child: import sdfr from the baseline's tree before anything else, then the
#: bench and the simulator (`sdfr.testing`) from this checkout; the rest of sdfr stays the
#: baseline's, already imported.
_LAUNCH = """
import importlib.util, runpy, sys
core, root = sys.argv[1], sys.argv[2]
sys.path[:] = [p for p in sys.path if p not in ("", ".", root)]
sys.path.insert(0, core)
import sdfr
assert sdfr.__file__.startswith(core), sdfr.__file__
testing = root + "/sdfr/testing"
spec = importlib.util.spec_from_file_location(
    "sdfr.testing", testing + "/__init__.py", submodule_search_locations=[testing]
)
sdfr.testing = sys.modules["sdfr.testing"] = importlib.util.module_from_spec(spec)
spec.loader.exec_module(sdfr.testing)
sys.path[0] = root
sys.argv = ["bench.auth", *sys.argv[3:]]
runpy.run_module("bench.auth", run_name="__main__", alter_sys=True)
"""


def baseline_tree(spec: str, tmp: Path) -> Path:
    """A directory holding the baseline's sdfr package: `spec` itself when it is one (a
    checkout, a worktree), else the revision `spec` of this repository extracted there."""
    path = Path(spec)
    if (path / "sdfr" / "__init__.py").exists():
        return path.resolve()
    rev = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--verify", f"{spec}^{{commit}}"],
        capture_output=True,
        text=True,
    )
    if rev.returncode != 0:
        raise SystemExit(f"bench: --baseline {spec}: neither a checkout nor a revision")
    tmp.mkdir(parents=True, exist_ok=True)
    archive = tmp / "sdfr.tar"
    with archive.open("wb") as f:
        subprocess.run(
            ["git", "-C", str(ROOT), "archive", "--format=tar", rev.stdout.strip(), "sdfr"],
            stdout=f,
            check=True,
        )
    with tarfile.open(archive) as tar:
        tar.extractall(tmp, filter="data")
    described = subprocess.run(
        ["git", "-C", str(ROOT), "describe", "--always", "--tags", rev.stdout.strip()],
        capture_output=True,
        text=True,
    ).stdout.strip()
    (tmp / ".bench-revision").write_text(described + "\n")
    return tmp


def run_baseline(spec: str, argv: list[str]) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="bench-auth-baseline-") as d:
        tmp = Path(d)
        tree = baseline_tree(spec, tmp / "tree")
        out = tmp / "baseline.json"
        env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
        cmd = [sys.executable, "-c", _LAUNCH, str(tree), str(ROOT), *argv, "--out", str(out)]
        res = subprocess.run(cmd, env=env, cwd=tmp, stdout=subprocess.DEVNULL)
        if res.returncode != 0:
            raise SystemExit(f"bench: the baseline run failed (status {res.returncode})")
        result: dict[str, Any] = json.loads(out.read_text())
        return result


def run_with_core(spec: str, argv: list[str]) -> int:
    """This bench, run in a child process against the sdfr of `spec` (see `baseline_tree`)."""
    with tempfile.TemporaryDirectory(prefix="bench-auth-core-") as d:
        tree = baseline_tree(spec, Path(d) / "tree")
        env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
        cmd = [sys.executable, "-c", _LAUNCH, str(tree), str(ROOT), *argv]
        return subprocess.run(cmd, env=env, cwd=d).returncode


def leaves(obj: object, path: str = "") -> Iterator[tuple[str, float | None]]:
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from leaves(v, f"{path}.{k}" if path else str(k))
    elif isinstance(obj, bool):
        return
    elif isinstance(obj, (int, float)) or obj is None:
        yield path, obj


SKIP = ("baseline", "side_by_side", "core", "started", "wall_s")


def side_by_side(old: dict[str, Any], new: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Every number of both runs, by its path in the JSON: baseline, this one, and the change."""
    olds = dict(leaves({k: v for k, v in old.items() if k not in SKIP}))
    news = dict(leaves({k: v for k, v in new.items() if k not in SKIP}))
    out: dict[str, dict[str, Any]] = {}
    for path in list(dict.fromkeys([*olds, *news])):
        a, b = olds.get(path), news.get(path)
        row: dict[str, Any] = {"old": a, "new": b}
        if isinstance(a, (int, float)) and isinstance(b, (int, float)):
            row["change"] = round(b - a, 3)
            if a:
                row["change_pct"] = round(100 * (b / a - 1), 1)
        out[path] = row
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench.auth", description=__doc__.splitlines()[0])
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


def report(result: dict[str, Any]) -> None:
    err = sys.stderr
    print(f"\n{'datagram':34} {'unsigned':>9} {'signed':>7} {'+bytes':>7} {'+%':>6}", file=err)
    for kind, row in result["bytes_per_datagram"].items():
        print(
            f"{kind:34} {row['unsigned']:9.0f} {row['signed']:7.0f} {row['overhead']:7.0f} "
            f"{row['overhead_pct']:6.1f}",
            file=err,
        )
    print("\nCPU, µs per datagram (median):", file=err)
    for label, row in result["cpu_per_datagram"].items():
        print(
            f"  {label:18} seal {row['seal_us']:6.2f}  check {row['check_us']:6.2f}  "
            f"check of an unsigned one {row['check_unsigned_us']:5.2f}",
            file=err,
        )
    rp = result["receive_path"]
    print(
        f"  whole receive path: unsigned {rp['unsigned_us']:.1f}, signed {rp['signed_us']:.1f} "
        f"(+{rp['overhead_us']:.1f})",
        file=err,
    )
    fl = result["fleet"]
    print(f"\nFleet ({fl['conditions']}):", file=err)
    for label in ("open", "keyed"):
        row = fl[label]
        print(
            f"  {label:5} TX {row['tx_kb_per_robot_5min']:7.1f} kB  "
            f"RX {row['rx_kb_per_robot_5min']:7.1f} kB per robot per 5 min "
            f"(start-up: TX {row['startup_tx_kb_per_robot']:.1f}, "
            f"RX {row['startup_rx_kb_per_robot']:.1f} kB)",
            file=err,
        )
    print(
        f"  keyed: TX {fl['tx_overhead_pct']:+.1f} %, RX {fl['rx_overhead_pct']:+.1f} %", file=err
    )
    dy = result["dynamics"]
    print("\nDynamics (s: median / max):", file=err)
    for label in ("open", "keyed"):
        side = dy[label]
        for dlabel in DELAYS:
            row = side[dlabel]
            cells = "  ".join(
                f"{what} {row[what]['median_s']} / {row[what]['max_s']}"
                for what in (*WHATS, "change_seen")
            )
            print(f"  {label:5} {dlabel:8} {cells}", file=err)
        print(f"  {label:5} link delays on the path: {side['link_delays_on_the_path']}", file=err)
        for what in ("idle", "churn"):
            row = side[what]
            print(
                f"  {label:5} {what:5} TX {row['tx_bytes_per_robot_min']:8.1f} B/min "
                f"({row['tx_datagrams_per_robot_min']:.1f} datagrams)  "
                f"RX {row['rx_bytes_per_robot_min']:8.1f} B/min per robot",
                file=err,
            )
    print(f"\nwall time {result['wall_s']} s; sdfr {result['core']}", file=err)
    if "side_by_side" in result:
        old = result["baseline"]["core"]
        print(f"\nSide by side: old = {old['git']} ({old['sdfr']}), new = this run", file=err)
        print(f"{'figure':96} {'old':>12} {'new':>12} {'change':>10}", file=err)
        for path, row in result["side_by_side"].items():
            a, b = row["old"], row["new"]
            ch = row.get("change_pct")
            print(
                f"{path[:96]:96} {fmt(a):>12} {fmt(b):>12} "
                f"{'' if ch is None else f'{ch:+.1f} %':>10}",
                file=err,
            )


def fmt(v: float | None) -> str:
    if v is None:
        return "-"
    return f"{v:.3f}".rstrip("0").rstrip(".") if isinstance(v, float) else str(v)


if __name__ == "__main__":
    raise SystemExit(main())
