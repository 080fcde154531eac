"""Who hears whom: positions and a range model, overridden by partitions and pair quality.

Pure code (no kernel): `Topology.links()` is the ground truth the medium
enforces and tests compare neighbour lists with. A link is an ordered pair
``(sender, receiver)`` mapped to its loss in percent (0 = clean).

Precedence, from strongest:

1. a partition cuts every link between its groups (robots named in no
   group form one more group together);
2. a pair quality set with `set_pair_quality` replaces the range model's
   loss for that ordered pair (100 cuts it); it never creates a link the
   range model or the partition does not give;
3. the range model turns the distance into "no link" or a loss.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

from netlab.errors import UnknownRobotError

Pos = tuple[float, float]
Pair = tuple[str, str]
Links = dict[Pair, float]


def linked_pairs(links: Iterable[Pair]) -> int:
    """Unordered pairs among these (sender, receiver) links: linked in at least one direction."""
    return len({frozenset(p) for p in links})


class RangeModel(Protocol):
    """Distance in metres to link quality."""

    def loss(self, distance: float) -> float | None:
        """Loss in percent at `distance`, or None when out of range."""
        ...


@dataclass(frozen=True, slots=True)
class UnitDisc:
    """Clean link up to `radius` metres, none beyond."""

    radius: float = 50.0

    def __post_init__(self) -> None:
        if not self.radius >= 0:
            raise ValueError(f"radius must be >= 0 metres, got {self.radius}")

    def loss(self, distance: float) -> float | None:
        return 0.0 if distance <= self.radius else None


@dataclass(frozen=True, slots=True)
class LossyDisc:
    """Clean up to `clean` metres, loss rising linearly to `edge_loss` % at `radius`, then none."""

    radius: float
    clean: float = 0.0
    edge_loss: float = 50.0

    def __post_init__(self) -> None:
        if not 0 <= self.clean <= self.radius:
            raise ValueError(
                f"need 0 <= clean <= radius, got clean={self.clean} radius={self.radius}"
            )
        if not 0 <= self.edge_loss <= 100:
            raise ValueError(f"edge_loss must be 0-100 %, got {self.edge_loss}")

    def loss(self, distance: float) -> float | None:
        if distance > self.radius:
            return None
        if distance <= self.clean or self.radius == self.clean:
            return 0.0
        return self.edge_loss * (distance - self.clean) / (self.radius - self.clean)


def model_to_json(model: RangeModel) -> dict[str, Any] | None:
    """The range model as JSON, or None for one netlab does not know (made in Python)."""
    if isinstance(model, UnitDisc):
        return {"kind": "unit-disc", "radius": model.radius}
    if isinstance(model, LossyDisc):
        return {
            "kind": "lossy-disc",
            "radius": model.radius,
            "clean": model.clean,
            "edge_loss": model.edge_loss,
        }
    return None


def model_from_json(data: dict[str, Any]) -> RangeModel:
    kind = data.get("kind")
    if kind == "unit-disc":
        return UnitDisc(float(data["radius"]))
    if kind == "lossy-disc":
        return LossyDisc(float(data["radius"]), float(data["clean"]), float(data["edge_loss"]))
    raise ValueError(f"unknown range model {kind!r}")


def combine(*losses: float) -> float:
    """The loss of independent drops in series, in percent."""
    nonzero = [loss for loss in losses if loss]
    if len(nonzero) <= 1:  # exact, without float noise from 1 - (1 - p)
        return float(nonzero[0]) if nonzero else 0.0
    keep = 1.0
    for loss in nonzero:
        keep *= 1.0 - loss / 100.0
    return 100.0 * (1.0 - keep)


def with_link_loss(links: Mapping[Pair, float], link_loss: Mapping[str, float]) -> Links:
    """`links` with each robot's own link loss added on every pair from or to it."""
    return {
        (a, b): combine(loss, link_loss.get(a, 0.0), link_loss.get(b, 0.0))
        for (a, b), loss in links.items()
    }


def forwarded(links: Mapping[Pair, float], relays: Iterable[str]) -> Links:
    """`links` as a mesh that forwards (802.11s): between `relays`, a pair is linked through
    any chain of relays, with the loss of its best chain (the most delivered, hops in series).
    Links from or to a robot not among `relays` stay as they are."""
    mesh = set(relays)
    keep = {p: 1.0 - loss / 100.0 for p, loss in links.items() if loss < 100.0}
    best = {p: k for p, k in keep.items() if set(p) <= mesh}
    nodes = sorted(mesh)
    for via in nodes:  # Floyd-Warshall on delivery, the product of the hops'
        into = [(a, k) for a in nodes if (k := best.get((a, via))) is not None]
        out_of = [(b, k) for b in nodes if (k := best.get((via, b))) is not None]
        for a, ka in into:
            for b, kb in out_of:
                if a != b and ka * kb > best.get((a, b), 0.0):
                    best[(a, b)] = ka * kb
    out = dict(links)
    for pair, k in best.items():
        if k > keep.get(pair, 0.0):  # a chain delivers more than the direct link, or is one
            out[pair] = 100.0 * (1.0 - k)
    return out


def check_loss(loss: float, what: str = "loss") -> float:
    if not 0 <= loss <= 100:
        raise ValueError(f"{what} must be 0-100 %, got {loss}")
    return float(loss)


class Topology:
    """Robot positions plus partition and pair overrides; `links()` is the result."""

    def __init__(self, model: RangeModel | None = None) -> None:
        self.model: RangeModel = model if model is not None else UnitDisc()
        self.positions: dict[str, Pos] = {}
        self.groups: list[frozenset[str]] | None = None
        self.pair_loss: dict[Pair, float] = {}

    def _known(self, *robots: str) -> None:
        for r in robots:
            if r not in self.positions:
                raise UnknownRobotError(f"no robot named {r!r} (robots: {sorted(self.positions)})")

    def add(self, robot: str, pos: Pos = (0.0, 0.0)) -> None:
        self.positions[robot] = _pos(pos)

    def move(self, robot: str, pos: Pos) -> None:
        self._known(robot)
        self.positions[robot] = _pos(pos)

    def partition(self, groups: Iterable[Iterable[str]]) -> None:
        """Cut every link between `groups`; robots in no group form one more group."""
        parts = [frozenset(g) for g in groups]
        seen: set[str] = set()
        for g in parts:
            self._known(*sorted(g))
            if seen & g:
                raise ValueError(f"robots in more than one group: {sorted(seen & g)}")
            seen |= g
        self.groups = [g for g in parts if g]

    def merge(self) -> None:
        """Undo the partition: the range model alone decides again."""
        self.groups = None

    def set_pair_quality(self, a: str, b: str, loss: float | None, both: bool = True) -> None:
        """Loss of a→b (and b→a if `both`) while linked; None returns it to the range model."""
        self._known(a, b)
        if a == b:
            raise ValueError(f"a pair needs two robots, got {a!r} twice")
        pairs = [(a, b), (b, a)] if both else [(a, b)]
        for pair in pairs:
            if loss is None:
                self.pair_loss.pop(pair, None)
            else:
                self.pair_loss[pair] = check_loss(loss)

    def to_json(self) -> dict[str, Any] | None:
        """Positions, partition and pair quality as JSON; None if the range model is not
        one netlab can write down."""
        model = model_to_json(self.model)
        if model is None:
            return None
        return {
            "model": model,
            "positions": {r: list(p) for r, p in self.positions.items()},
            "groups": None if self.groups is None else [sorted(g) for g in self.groups],
            "pair_loss": [[a, b, loss] for (a, b), loss in sorted(self.pair_loss.items())],
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Topology:
        topo = cls(model_from_json(data["model"]))
        for robot, pos in data["positions"].items():
            topo.add(robot, (pos[0], pos[1]))
        if data.get("groups") is not None:
            topo.partition(data["groups"])
        for a, b, loss in data.get("pair_loss", []):
            topo.set_pair_quality(a, b, loss, both=False)
        return topo

    def group_of(self, robot: str) -> int:
        """Index of the robot's partition group (len(groups) for the unnamed rest)."""
        assert self.groups is not None
        for i, g in enumerate(self.groups):
            if robot in g:
                return i
        return len(self.groups)

    def links(self) -> Links:
        """Every linked ordered pair and its loss in percent."""
        out: Links = {}
        names = sorted(self.positions)
        group = {r: self.group_of(r) for r in names} if self.groups is not None else None
        for a in names:
            for b in names:
                if a == b or (group is not None and group[a] != group[b]):
                    continue
                loss = self.model.loss(distance(self.positions[a], self.positions[b]))
                if loss is None:
                    continue
                loss = self.pair_loss.get((a, b), loss)
                if loss < 100.0:
                    out[(a, b)] = loss
        return out


def distance(p: Pos, q: Pos) -> float:
    return math.hypot(p[0] - q[0], p[1] - q[1])


def _pos(pos: Pos) -> Pos:
    x, y = float(pos[0]), float(pos[1])
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ValueError(f"position must be finite, got {pos}")
    return (x, y)
