"""Watching a running fleet: what each robot's sdfrd lists, against the medium's truth.

* `Probe` asks the robots' daemons over their REST API (one client per robot; one probe per
  thread, since a client is not shared between threads);
* `TruthLog` records, each time it changes, which pairs the medium links and which daemons
  run: what every neighbour list should say;
* `Observer` samples the neighbour lists in the background, for the report's plots and the
  agreement check;
* the functions below judge a snapshot ("r4 lists {r1, r2} but should list {r1, r2, r3}") or
  a series of samples (agreement with the truth, allowing a detection lag).  They are pure, so
  they are tested without root.

Times are UNIX seconds (``time.time()``), the clock of the pcaps and the report.
"""

from __future__ import annotations

import bisect
import threading
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

from netlab.analysis import natural_order
from netlab.clock import REAL, Clock
from netlab.report import AgreementSample, ConnectivitySample
from sdfr.errors import ApiError

__all__ = [
    "AgreementStats",
    "ClientLike",
    "FlapStats",
    "Observer",
    "PeerEntry",
    "Probe",
    "Sample",
    "TruthLog",
    "TruthState",
    "View",
    "address_problems",
    "agreement",
    "connectivity",
    "expect_problems",
    "flaps",
    "fmt_set",
    "history_problems",
    "indicator_problems",
    "indicators_before",
    "unreachable_problems",
]

Pair = tuple[str, str]
#: At most this many problems are spelled out in one message.
MAX_PROBLEMS = 6


class ClientLike(Protocol):
    """What the scenario engine needs of `sdfr.client.Client`."""

    def neighbors(self, include_unreachable: bool = False) -> list[dict[str, Any]]: ...

    def history(self) -> list[dict[str, Any]]: ...

    def publish(
        self,
        name: str,
        type: str,
        url: str | None = None,
        attributes: Mapping[str, Any] | None = None,
    ) -> str: ...

    def unpublish(self, service_id: str) -> None: ...

    def self_info(self) -> dict[str, object]: ...

    def close(self) -> None: ...


# ---------------------------------------------------------------------------------------------
# What a robot lists


@dataclass(frozen=True, slots=True)
class PeerEntry:
    """One entry of a neighbour list or history map."""

    robot_id: str
    reachable: bool
    address: str = ""
    services: frozenset[str] = frozenset()
    indicator: float | None = None

    @classmethod
    def from_json(cls, obj: Mapping[str, Any]) -> PeerEntry:
        ind = obj.get("indicator")
        return cls(
            robot_id=str(obj.get("robot_id", "?")),
            reachable=bool(obj.get("reachable", True)),
            address=str(obj.get("address") or ""),
            services=frozenset(
                str(s.get("name")) for s in obj.get("services") or () if isinstance(s, Mapping)
            ),
            indicator=float(ind) if isinstance(ind, int | float) else None,
        )


@dataclass(frozen=True, slots=True)
class View:
    """One robot's neighbour list (or history map), or why it could not be had."""

    entries: tuple[PeerEntry, ...] = ()
    error: str | None = None

    @property
    def reachable(self) -> frozenset[str]:
        """The robots it lists as reachable now."""
        return frozenset(e.robot_id for e in self.entries if e.reachable)

    def entry(self, robot: str) -> PeerEntry | None:
        return next((e for e in self.entries if e.robot_id == robot), None)

    def duplicates(self) -> list[str]:
        """Robots listed more than once."""
        counts = Counter(e.robot_id for e in self.entries)
        return natural_order([r for r, n in counts.items() if n > 1])


class Probe:
    """Asks robots' daemons what they list; errors become a `View` with `error` set."""

    def __init__(self, connect: Callable[[str], ClientLike]) -> None:
        self._connect = connect
        self._clients: dict[str, ClientLike] = {}

    def client(self, robot: str) -> ClientLike:
        if robot not in self._clients:
            self._clients[robot] = self._connect(robot)
        return self._clients[robot]

    def neighbours(self, robots: Iterable[str]) -> dict[str, View]:
        """Each robot's reachable neighbours."""
        return {r: self._ask(r, lambda c: c.neighbors()) for r in robots}

    def histories(self, robots: Iterable[str]) -> dict[str, View]:
        """Each robot's history map: every robot it ever heard."""
        return {r: self._ask(r, lambda c: c.history()) for r in robots}

    def addresses(self, robots: Iterable[str]) -> dict[str, str]:
        """Each robot's own address (``GET /self``): "" before it has one, or "error: ..."."""
        out: dict[str, str] = {}
        for robot in robots:
            try:
                out[robot] = str(self.client(robot).self_info().get("address") or "")
            except ApiError as exc:
                out[robot] = f"error: {exc}"
        return out

    def _ask(self, robot: str, call: Callable[[ClientLike], list[dict[str, Any]]]) -> View:
        try:
            found = call(self.client(robot))
        except ApiError as exc:
            return View(error=str(exc))
        return View(tuple(PeerEntry.from_json(e) for e in found if isinstance(e, Mapping)))

    def close(self) -> None:
        for client in self._clients.values():
            client.close()
        self._clients.clear()


# ---------------------------------------------------------------------------------------------
# Ground truth


@dataclass(frozen=True, slots=True)
class TruthState:
    """From `time` on: the medium's links (sender, receiver) and the daemons that run."""

    time: float
    links: frozenset[Pair]
    running: frozenset[str]

    def hears(self, robot: str, peer: str) -> bool:
        """Whether `robot`'s list should show `peer` as reachable."""
        return robot in self.running and peer in self.running and (peer, robot) in self.links

    def expected(self, robot: str) -> set[str]:
        """The peers `robot` should list as reachable."""
        if robot not in self.running:
            return set()
        return {a for (a, b) in self.links if b == robot and a in self.running}

    def linked_pairs(self) -> int:
        """Unordered pairs the medium links (in at least one direction)."""
        return len({frozenset(p) for p in self.links})

    def to_json(self) -> dict[str, object]:
        return {
            "time": self.time,
            "links": sorted([a, b] for a, b in self.links),
            "running": natural_order(list(self.running)),
        }

    @classmethod
    def from_json(cls, obj: Mapping[str, Any]) -> TruthState:
        return cls(
            float(obj["time"]),
            frozenset((str(a), str(b)) for a, b in obj.get("links", ())),
            frozenset(str(r) for r in obj.get("running", ())),
        )


class TruthLog:
    """The truth over time: a state appended each time the links or the running set change.

    Written by the thread that changes the lab, read by the observer: guarded by a lock.
    """

    def __init__(self, clock: Callable[[], float] = time.time) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        self._states: list[TruthState] = []

    def record(self, links: Iterable[Pair], running: Iterable[str]) -> TruthState:
        state = TruthState(self._clock(), frozenset(links), frozenset(running))
        with self._lock:
            last = self._states[-1] if self._states else None
            if last is not None and (last.links, last.running) == (state.links, state.running):
                return last
            self._states.append(state)
        return state

    def now(self) -> TruthState:
        with self._lock:
            if not self._states:
                return TruthState(self._clock(), frozenset(), frozenset())
            return self._states[-1]

    def states(self) -> list[TruthState]:
        with self._lock:
            return list(self._states)


def _in_force(
    states: Sequence[TruthState], times: Sequence[float], t0: float, t1: float
) -> Sequence[TruthState]:
    """The states in force at some moment of [t0, t1] (`times`: their start times)."""
    hi = bisect.bisect_right(times, t1) - 1
    if hi < 0:
        return ()
    lo = max(0, bisect.bisect_right(times, t0) - 1)
    return states[lo : hi + 1]


# ---------------------------------------------------------------------------------------------
# Samples


@dataclass(frozen=True, slots=True)
class Sample:
    """What the robots listed as reachable at `time` (robots that could not be asked: absent),
    and (`indicators`) the connection indicator each gave each peer it listed."""

    time: float
    seen: Mapping[str, frozenset[str]]
    indicators: Mapping[str, Mapping[str, float]] = field(default_factory=dict)

    def to_json(self) -> dict[str, object]:
        out: dict[str, Any] = {
            "time": self.time,
            "seen": {a: natural_order(list(s)) for a, s in self.seen.items()},
        }
        if self.indicators:
            out["indicators"] = {a: dict(sorted(i.items())) for a, i in self.indicators.items()}
        return out

    @classmethod
    def from_json(cls, obj: Mapping[str, Any]) -> Sample:
        seen = obj.get("seen") or {}
        ind = obj.get("indicators") or {}
        return cls(
            float(obj["time"]),
            {str(a): frozenset(map(str, s)) for a, s in seen.items()},
            {str(a): {str(b): float(v) for b, v in i.items()} for a, i in ind.items()},
        )


class Observer:
    """Samples the running robots' neighbour lists every `period` seconds of `clock` (in a
    thread with the real clock; as virtual time passes with a `VirtualClock`)."""

    def __init__(
        self,
        probe: Probe,
        truth: TruthLog,
        period: float = 0.25,
        clock: Clock = REAL,
    ) -> None:
        if period <= 0:
            raise ValueError(f"period must be positive, not {period}")
        self.probe = probe
        self.truth = truth
        self.period = period
        self._clock = clock
        self._samples: list[Sample] = []
        self._lock = threading.Lock()
        self._cancel: Callable[[], None] | None = None

    def start(self) -> Observer:
        self._cancel = self._clock.every(self.period, self.sample)
        return self

    def stop(self) -> list[Sample]:
        """Stop sampling (idempotent); the samples taken."""
        if self._cancel is not None:
            self._cancel()
            self._cancel = None
        self.probe.close()
        return self.samples

    @property
    def samples(self) -> list[Sample]:
        with self._lock:
            return list(self._samples)

    def sample(self) -> None:
        """Take one sample now."""
        t = self._clock.time()
        running = natural_order(list(self.truth.now().running))
        views = self.probe.neighbours(running)
        seen = {a: v.reachable for a, v in views.items() if v.error is None}
        indicators = {
            a: {e.robot_id: e.indicator for e in v.entries if e.indicator is not None}
            for a, v in views.items()
            if v.error is None
        }
        with self._lock:
            self._samples.append(Sample(t, seen, indicators))


# ---------------------------------------------------------------------------------------------
# Judging a snapshot: a list of problems, empty when the condition holds


def fmt_set(names: Iterable[str]) -> str:
    """``{r1, r2, r10}``, in human order."""
    return "{" + ", ".join(natural_order(list(names))) + "}"


def _summary(problems: list[str]) -> list[str]:
    if len(problems) <= MAX_PROBLEMS:
        return problems
    return [*problems[:MAX_PROBLEMS], f"and {len(problems) - MAX_PROBLEMS} more"]


def expect_problems(
    views: Mapping[str, View],
    expected: Mapping[str, Iterable[str]],
    *,
    services: Mapping[str, Iterable[str]] | None = None,
    exact: bool = True,
) -> list[str]:
    """Each robot of `expected` lists those peers as reachable (`exact`: and no others), each
    once, and (with `services`) each with exactly the services named there for it."""
    problems: list[str] = []
    for robot in natural_order(list(expected)):
        want = set(expected[robot]) - {robot}
        view = views.get(robot, View(error="not asked"))
        if view.error is not None:
            problems.append(f"{robot}: {view.error}")
            continue
        listed = set(view.reachable)
        if (exact and listed != want) or not want <= listed:
            if exact:
                problems.append(f"{robot} lists {fmt_set(listed)} but should list {fmt_set(want)}")
            else:
                problems.append(
                    f"{robot} lists {fmt_set(listed)}, without {fmt_set(want - listed)}"
                )
        for dup in view.duplicates():
            problems.append(f"{robot} lists {dup} more than once")
        if services is None:
            continue
        for peer in natural_order(list(want & listed)):
            entry = view.entry(peer)
            have = set(entry.services) if entry is not None else set()
            should = set(services.get(peer, ()))
            if have != should:
                problems.append(
                    f"{robot} lists {peer} with services {fmt_set(have)}, but {peer} publishes "
                    f"{fmt_set(should)}"
                )
    return _summary(problems)


def unreachable_problems(
    views: Mapping[str, View], robots: Iterable[str], on: Iterable[str]
) -> list[str]:
    """None of `on` lists any of `robots` as reachable."""
    gone = set(robots)
    problems: list[str] = []
    for robot in natural_order(list(on)):
        view = views.get(robot, View(error="not asked"))
        if view.error is not None:
            problems.append(f"{robot}: {view.error}")
        elif view.reachable & gone:
            problems.append(f"{robot} still lists {fmt_set(view.reachable & gone)} as reachable")
    return _summary(problems)


def history_problems(
    histories: Mapping[str, View],
    robots: Iterable[str],
    on: Iterable[str],
    *,
    reachable: bool | None = None,
    indicator_below: float | None = None,
    fell_from: Mapping[str, Mapping[str, float]] | None = None,
) -> list[str]:
    """Each of `on` holds every one of `robots` in its history map (as reachable or not, and
    with its connection indicator below a bound, when asked); with `fell_from` (robot -> peer
    -> indicator seen earlier), each indicator must have fallen below that earlier value."""
    wanted = natural_order(list(set(robots)))
    problems: list[str] = []
    for robot in natural_order(list(on)):
        view = histories.get(robot, View(error="not asked"))
        if view.error is not None:
            problems.append(f"{robot}: {view.error}")
            continue
        missing = [r for r in wanted if r != robot and view.entry(r) is None]
        if missing:
            problems.append(f"{fmt_set(missing)} missing from the history of {robot}")
        for peer in wanted:
            entry = view.entry(peer)
            if entry is None or peer == robot:
                continue
            if reachable is not None and entry.reachable != reachable:
                state = "reachable" if entry.reachable else "unreachable"
                problems.append(f"{robot}'s history has {peer} as {state}")
            if indicator_below is not None and not (
                entry.indicator is not None and entry.indicator < indicator_below
            ):
                problems.append(
                    f"{robot} rates {peer} at indicator {entry.indicator}, "
                    f"not below {indicator_below:g}"
                )
            if fell_from is not None:
                was = fell_from.get(robot, {}).get(peer)
                if was is None:
                    problems.append(f"no indicator of {robot} for {peer} was sampled before")
                elif not (entry.indicator is not None and entry.indicator < was):
                    problems.append(
                        f"{robot}'s indicator for {peer} did not fall: {entry.indicator} "
                        f"now, {was:g} before"
                    )
    return _summary(problems)


def indicator_problems(
    views: Mapping[str, View], rates: Mapping[Pair, float], tolerance: float
) -> list[str]:
    """Each robot's connection indicator for each peer it lists is within `tolerance` of
    `rates[(robot, peer)]`, the share of its pings to that peer that can come back (the ping
    and its reply both cross the medium)."""
    problems: list[str] = []
    for robot in natural_order(list(views)):
        view = views[robot]
        if view.error is not None:
            problems.append(f"{robot}: {view.error}")
            continue
        for peer in natural_order(list(view.reachable)):
            rate = rates.get((robot, peer))
            if rate is None:
                continue
            entry = view.entry(peer)
            ind = entry.indicator if entry is not None else None
            if ind is None:
                problems.append(f"{robot} has no indicator for {peer} yet")
            elif abs(ind - rate) > tolerance:
                problems.append(
                    f"{robot} rates {peer} at {ind:.2f}, the medium delivers {rate:.2f} "
                    f"round trip (allowed: +-{tolerance:g})"
                )
    return _summary(problems)


def address_problems(views: Mapping[str, View], own: Mapping[str, str] | None = None) -> list[str]:
    """Every robot has an address of its own (`own`: robot -> its address, from ``/self``), and
    no two robots are listed at the same address, in one list or across lists."""
    problems: list[str] = []
    owners: dict[str, set[str]] = defaultdict(set)
    for robot, addr in sorted((own or {}).items()):
        if addr.startswith("error: "):
            problems.append(f"{robot}: {addr[7:]}")
        elif not addr:
            problems.append(f"{robot} has no address yet")
        else:
            owners[addr].add(robot)
    for robot in natural_order(list(views)):
        view = views[robot]
        if view.error is not None:
            problems.append(f"{robot}: {view.error}")
            continue
        for entry in view.entries:
            if entry.reachable and entry.address:
                owners[entry.address].add(entry.robot_id)
    for addr, ids in sorted(owners.items()):
        if len(ids) > 1:
            problems.append(f"{fmt_set(ids)} are listed at the same address {addr}")
    return _summary(problems)


# ---------------------------------------------------------------------------------------------
# Judging samples: agreement with the truth, allowing a detection lag


@dataclass(frozen=True, slots=True)
class AgreementStats:
    """Neighbour lists against the truth over a window of samples.

    An observation is one ordered pair (robot, peer) in one sample; it agrees when whether the
    robot lists the peer matches the truth at some moment of the `lag` seconds before the
    sample (a list may be late by up to `lag`); for a peer it lists, `loss_lag` (a vanished
    link may be noticed that late).

    pair_share: agreeing observations / all observations;
    sample_share: samples in which every observation agrees / samples;
    stale: disagreeing observations of a peer listed but not linked; missing: linked but not
    listed;
    per_sample: each sample's share, for the report;
    worst: (robot, peer, share of samples disagreeing), most disagreeing first.
    """

    samples: int
    observations: int
    pair_share: float
    sample_share: float
    stale: int = 0
    missing: int = 0
    per_sample: list[AgreementSample] = field(default_factory=list)
    worst: list[tuple[str, str, float]] = field(default_factory=list)

    def to_json(self) -> dict[str, object]:
        return {
            "samples": self.samples,
            "observations": self.observations,
            "pair_share": self.pair_share,
            "sample_share": self.sample_share,
            "stale": self.stale,
            "missing": self.missing,
            "worst": [list(w) for w in self.worst[:MAX_PROBLEMS]],
        }


def agreement(
    samples: Iterable[Sample],
    truth: Sequence[TruthState],
    *,
    lag: float = 0.0,
    loss_lag: float | None = None,
    start: float = float("-inf"),
    end: float = float("inf"),
) -> AgreementStats:
    """How far the sampled lists in [start, end] agree with `truth` (see `AgreementStats`)."""
    states = sorted(truth, key=lambda s: s.time)
    times = [s.time for s in states]
    loss_lag = lag if loss_lag is None else loss_lag
    per_sample: list[AgreementSample] = []
    observations = agreeing = full = stale = missing = 0
    misses: Counter[Pair] = Counter()
    seen_pairs: Counter[Pair] = Counter()
    for sample in samples:
        if not start <= sample.time <= end:
            continue
        appear = _in_force(states, times, sample.time - lag, sample.time)
        vanish = _in_force(states, times, sample.time - loss_lag, sample.time)
        if not appear:
            continue
        running = set().union(*(s.running for s in (*appear, *vanish)))
        per_robot: dict[str, float] = {}
        total = ok = 0
        for robot in natural_order(list(sample.seen)):
            listed = sample.seen[robot]
            mine = good = 0
            for peer in natural_order(list((running | listed) - {robot})):
                value = peer in listed
                window = vanish if value else appear
                right = any(s.hears(robot, peer) == value for s in window)
                mine += 1
                good += right
                seen_pairs[(robot, peer)] += 1
                if not right:
                    misses[(robot, peer)] += 1
                    stale += value
                    missing += not value
            if mine:
                per_robot[robot] = good / mine
            total += mine
            ok += good
        if not total:
            continue
        observations += total
        agreeing += ok
        full += ok == total
        per_sample.append(AgreementSample(sample.time, ok / total, per_robot))
    worst = sorted(
        ((a, b, n / seen_pairs[(a, b)]) for (a, b), n in misses.items()),
        key=lambda w: (-w[2], w[0], w[1]),
    )
    n = len(per_sample)
    return AgreementStats(
        samples=n,
        observations=observations,
        pair_share=agreeing / observations if observations else 1.0,
        sample_share=full / n if n else 1.0,
        stale=stale,
        missing=missing,
        per_sample=per_sample,
        worst=worst,
    )


@dataclass(frozen=True, slots=True)
class FlapStats:
    """Flaps over a window of samples: a flap is a peer the medium kept linked that a robot
    listed in one sample and not in the next one it answered.

    pairs: (robot, peer) pairs watched; flaps: in all; most: the most flaps of one pair within
    any `per` seconds; worst: (robot, peer, flaps), most first; at: robot -> peer -> times.
    """

    samples: int
    pairs: int
    flaps: int
    most: int
    per: float
    worst: list[tuple[str, str, int]] = field(default_factory=list)
    at: dict[str, dict[str, list[float]]] = field(default_factory=dict)

    def to_json(self) -> dict[str, object]:
        return {
            "samples": self.samples,
            "pairs": self.pairs,
            "flaps": self.flaps,
            "most_per_window": self.most,
            "window_s": self.per,
            "worst": [list(w) for w in self.worst[:MAX_PROBLEMS]],
        }


def flaps(
    samples: Iterable[Sample],
    truth: Sequence[TruthState],
    *,
    per: float = 60.0,
    start: float = float("-inf"),
    end: float = float("inf"),
) -> FlapStats:
    """Count flaps in [start, end] (see `FlapStats`): a drop counts only when the medium linked
    the pair and both daemons ran throughout, from the earlier sample to the later one."""
    states = sorted(truth, key=lambda s: s.time)
    times = [s.time for s in states]
    last: dict[str, tuple[float, frozenset[str]]] = {}
    at: dict[tuple[str, str], list[float]] = defaultdict(list)
    watched: set[tuple[str, str]] = set()
    n = 0
    for sample in sorted(samples, key=lambda s: s.time):
        if not start <= sample.time <= end:
            continue
        n += 1
        for robot, listed in sample.seen.items():
            before = last.get(robot)
            last[robot] = (sample.time, listed)
            if before is None:
                continue
            window = _in_force(states, times, before[0], sample.time)
            for peer in before[1]:
                if not window or not all(s.hears(robot, peer) for s in window):
                    continue
                watched.add((robot, peer))
                if peer not in listed:
                    at[(robot, peer)].append(sample.time)
    most = 0
    for ts in at.values():
        lo = 0
        for hi, t in enumerate(ts):
            while t - ts[lo] >= per:
                lo += 1
            most = max(most, hi - lo + 1)
    worst = sorted(((a, b, len(ts)) for (a, b), ts in at.items()), key=lambda w: (-w[2], w[:2]))
    table: dict[str, dict[str, list[float]]] = defaultdict(dict)
    for (a, b), ts in at.items():
        table[a][b] = ts
    return FlapStats(
        samples=n,
        pairs=len(watched),
        flaps=sum(len(ts) for ts in at.values()),
        most=most,
        per=per,
        worst=worst,
        at=dict(table),
    )


def indicators_before(samples: Sequence[Sample], t: float) -> dict[str, dict[str, float]]:
    """Each robot's latest indicator for each peer from the samples taken before `t`."""
    out: dict[str, dict[str, float]] = defaultdict(dict)
    for sample in sorted(samples, key=lambda s: s.time):
        if sample.time >= t:
            break
        for robot, ind in sample.indicators.items():
            out[robot].update(ind)
    return dict(out)


def connectivity(
    samples: Iterable[Sample], truth: Sequence[TruthState]
) -> list[ConnectivitySample]:
    """The report's connectivity series: medium links and reachable peers at each sample."""
    states = sorted(truth, key=lambda s: s.time)
    times = [s.time for s in states]
    out: list[ConnectivitySample] = []
    for sample in samples:
        window = _in_force(states, times, sample.time, sample.time)
        linked = window[-1].linked_pairs() if window else 0
        seen = sample.seen
        mutual = sum(1 for a in seen for b in seen[a] if a < b and a in seen.get(b, frozenset()))
        out.append(
            ConnectivitySample(
                sample.time, linked, {a: len(s) for a, s in seen.items()}, reachable_pairs=mutual
            )
        )
    return out
