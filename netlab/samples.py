"""Judging samples of the neighbour lists over time against the truth: agreement (allowing a
detection lag), flaps, and the connectivity and agreement series the report plots.  Pure, so
tested without root.

Times are UNIX seconds (``time.time()``), the clock of the pcaps and the report.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from netlab.analysis import natural_order
from netlab.judging import MAX_PROBLEMS
from netlab.truth import Pair, TruthState, in_force

__all__ = [
    "AgreementSample",
    "AgreementStats",
    "ConnectivitySample",
    "FlapStats",
    "Sample",
    "agreement",
    "connectivity",
    "flaps",
    "indicators_before",
]


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


@dataclass(frozen=True, slots=True)
class ConnectivitySample:
    """The fleet's connectivity at one moment.

    linked_pairs: unordered robot pairs the medium links (ground truth);
    reachable: per robot, how many peers its neighbour list says are reachable;
    reachable_pairs: unordered pairs in which both robots list each other (optional).
    """

    time: float
    linked_pairs: int
    reachable: Mapping[str, int] = field(default_factory=dict)
    reachable_pairs: int | None = None

    @classmethod
    def coerce(cls, obj: ConnectivitySample | Mapping[str, Any]) -> ConnectivitySample:
        if isinstance(obj, ConnectivitySample):
            return obj
        rp = obj.get("reachable_pairs")
        return cls(
            time=float(obj["time"] if "time" in obj else obj["t"]),
            linked_pairs=int(obj["linked_pairs"]),
            reachable={str(k): int(v) for k, v in dict(obj.get("reachable") or {}).items()},
            reachable_pairs=None if rp is None else int(rp),
        )

    def to_json(self) -> dict[str, object]:
        out: dict[str, Any] = {
            "time": self.time,
            "linked_pairs": self.linked_pairs,
            "reachable": dict(self.reachable),
        }
        if self.reachable_pairs is not None:
            out["reachable_pairs"] = self.reachable_pairs
        return out


@dataclass(frozen=True, slots=True)
class AgreementSample:
    """Neighbour tables against the medium's truth at one moment.

    agreement: 0..1, share of ordered (robot, peer) pairs on which they agree (see
    `agreement`); per_robot: the same per robot (optional).
    """

    time: float
    agreement: float
    per_robot: Mapping[str, float] = field(default_factory=dict)

    @classmethod
    def coerce(cls, obj: AgreementSample | Mapping[str, Any]) -> AgreementSample:
        if isinstance(obj, AgreementSample):
            return obj
        value = float(obj["agreement"])
        if not 0.0 <= value <= 1.0:
            raise ValueError(f"agreement must be within 0..1, not {value}")
        return cls(
            time=float(obj["time"] if "time" in obj else obj["t"]),
            agreement=value,
            per_robot={str(k): float(v) for k, v in dict(obj.get("per_robot") or {}).items()},
        )

    def to_json(self) -> dict[str, object]:
        out: dict[str, Any] = {"time": self.time, "agreement": self.agreement}
        if self.per_robot:
            out["per_robot"] = dict(self.per_robot)
        return out


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
        appear = in_force(states, times, sample.time - lag, sample.time)
        vanish = in_force(states, times, sample.time - loss_lag, sample.time)
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
            window = in_force(states, times, before[0], sample.time)
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
        window = in_force(states, times, sample.time, sample.time)
        linked = window[-1].linked_pairs() if window else 0
        seen = sample.seen
        mutual = sum(1 for a in seen for b in seen[a] if a < b and a in seen.get(b, frozenset()))
        out.append(
            ConnectivitySample(
                sample.time, linked, {a: len(s) for a, s in seen.items()}, reachable_pairs=mutual
            )
        )
    return out
