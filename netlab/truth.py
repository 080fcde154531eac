"""The medium's truth over time: which pairs it links and which daemons run, recorded each
time either changes; what every neighbour list should say.

Times are UNIX seconds (``time.time()``), the clock of the pcaps and the report.
"""

from __future__ import annotations

import bisect
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from netlab.analysis import natural_order
from netlab.ranges import linked_pairs

__all__ = ["Pair", "TruthLog", "TruthState", "in_force"]

Pair = tuple[str, str]


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
        return linked_pairs(self.links)

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


def in_force(
    states: Sequence[TruthState], times: Sequence[float], t0: float, t1: float
) -> Sequence[TruthState]:
    """The states in force at some moment of [t0, t1] (`times`: their start times)."""
    hi = bisect.bisect_right(times, t1) - 1
    if hi < 0:
        return ()
    lo = max(0, bisect.bisect_right(times, t0) - 1)
    return states[lo : hi + 1]
