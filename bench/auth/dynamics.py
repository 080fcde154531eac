"""A fleet's dynamics, open and keyed, at two link delays: joins, restarts (graceful and
after a kill), the bytes on the air of an idle and a churning fleet, how long a change takes
to be seen everywhere."""

from __future__ import annotations

import random
import statistics
from collections import Counter
from collections.abc import Callable
from functools import partial
from typing import Any

from bench.auth.fixtures import STARTUP_S, rings, services
from sdfr.protocol.auth import Keyring
from sdfr.records.model import Service
from sdfr.testing.simnet import SimNet, kind_of

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
