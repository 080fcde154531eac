"""Mobility models in virtual time: `positions_at(t)` depends only on the model and `t`.

`Lab.run_mobility` samples a model in real time and moves the robots; the
model itself never reads a clock, so it is tested by stepping `t`.
"""

from __future__ import annotations

import bisect
import random
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol

from netlab.ranges import Pos, distance

#: The paper's evaluation hall: 200 m².
HALL = (20.0, 10.0)


class MobilityModel(Protocol):
    robots: Sequence[str]

    def positions_at(self, t: float) -> dict[str, Pos]:
        """Where every robot of the model is at virtual time `t` (seconds, >= 0)."""
        ...


@dataclass(frozen=True, slots=True)
class _Leg:
    start: float  # leaves `origin`
    arrive: float  # reaches `target`, then pauses
    leave: float  # end of the pause: the next leg starts
    origin: Pos
    target: Pos


class _Track:
    """One robot's legs, generated on demand from its own random stream."""

    def __init__(self, model: RandomWaypoint, rng: random.Random, start: Pos) -> None:
        self.model = model
        self.rng = rng
        self.legs: list[_Leg] = []
        self.starts: list[float] = []
        self._here = start
        self._t = 0.0

    def _extend(self) -> None:
        m, rng = self.model, self.rng
        target = (rng.uniform(0.0, m.area[0]), rng.uniform(0.0, m.area[1]))
        speed = rng.uniform(*m.speed)
        arrive = self._t + distance(self._here, target) / speed
        leave = arrive + rng.uniform(*m.pause)
        self.legs.append(_Leg(self._t, arrive, leave, self._here, target))
        self.starts.append(self._t)
        self._here, self._t = target, leave

    def at(self, t: float) -> Pos:
        while self._t <= t:
            self._extend()
        leg = self.legs[bisect.bisect_right(self.starts, t) - 1]
        if t >= leg.arrive or leg.arrive == leg.start:
            return leg.target
        f = (t - leg.start) / (leg.arrive - leg.start)
        (x0, y0), (x1, y1) = leg.origin, leg.target
        return (x0 + f * (x1 - x0), y0 + f * (y1 - y0))


class RandomWaypoint:
    """Random waypoint in a `area` rectangle (metres): go to a uniform point at a uniform
    speed in `speed` (m/s), pause a uniform time in `pause` (s), repeat.

    Each robot draws from its own stream seeded by (`seed`, robot name), so adding a
    robot does not change the others' paths. Start points are uniform unless given.
    """

    def __init__(
        self,
        robots: Sequence[str],
        *,
        area: tuple[float, float] = HALL,
        speed: tuple[float, float] = (0.5, 1.5),
        pause: tuple[float, float] | float = (0.0, 2.0),
        seed: int = 0,
        start: Mapping[str, Pos] | None = None,
    ) -> None:
        if not (area[0] > 0 and area[1] > 0):
            raise ValueError(f"area must be positive (width, height) metres, got {area}")
        # A minimum speed of 0 would let robots crawl forever (the model's known decay).
        if not 0 < speed[0] <= speed[1]:
            raise ValueError(f"speed must be (min, max) m/s with 0 < min <= max, got {speed}")
        pauses = (float(pause), float(pause)) if isinstance(pause, int | float) else pause
        if not 0 <= pauses[0] <= pauses[1]:
            raise ValueError(f"pause must be (min, max) s with 0 <= min <= max, got {pause}")
        if len(set(robots)) != len(robots):
            raise ValueError(f"robot names repeat: {list(robots)}")
        self.robots: Sequence[str] = tuple(robots)
        self.area = (float(area[0]), float(area[1]))
        self.speed = (float(speed[0]), float(speed[1]))
        self.pause = (float(pauses[0]), float(pauses[1]))
        self.seed = seed
        self._tracks: dict[str, _Track] = {}
        for name in self.robots:
            rng = random.Random(f"netlab-rwp:{seed}:{name}")
            if start is not None and name in start:
                here = (float(start[name][0]), float(start[name][1]))
            else:
                here = (rng.uniform(0.0, self.area[0]), rng.uniform(0.0, self.area[1]))
            self._tracks[name] = _Track(self, rng, here)

    def positions_at(self, t: float) -> dict[str, Pos]:
        if t < 0:
            raise ValueError(f"t must be >= 0, got {t}")
        return {name: self._tracks[name].at(t) for name in self.robots}


def walk(
    model: MobilityModel,
    duration: float,
    tick: float,
    apply: Callable[[float, dict[str, Pos]], None],
    *,
    clock: Callable[[], float],
    sleep: Callable[[float], None],
) -> int:
    """Apply the model's positions at t = 0, tick, 2 tick, ... <= duration, each on time by
    `clock` (late ticks are not made up for by skipping: each is applied); the ticks done."""
    if tick <= 0 or duration < 0:
        raise ValueError(f"need tick > 0 and duration >= 0, got {tick}, {duration}")
    t0 = clock()
    k = 0
    while k * tick <= duration + 1e-9:
        apply(k * tick, model.positions_at(k * tick))
        k += 1
        wait = t0 + k * tick - clock()
        if wait > 0 and k * tick <= duration + 1e-9:
            sleep(wait)
    return k
