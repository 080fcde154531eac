"""The scenario: a fleet, its medium, and the timeline of steps it goes through."""

from __future__ import annotations

import random
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from netlab import naming
from netlab.errors import NetlabError
from netlab.hosts import DESTINATION_RE
from netlab.judging import fmt_set
from netlab.mobility import HALL
from netlab.ranges import Pos
from netlab.robots import AIR_MEDIA, AIRS, RUNTIMES
from netlab.scenario.spec import (
    KEYWORDS,
    Bad,
    ScenarioError,
    Selectors,
    area_size,
    bounded,
    check_field,
    check_options,
    seconds,
    to_int,
    to_names,
    toml,
)
from netlab.scenario.steps import Check, Collision, Mobility, Sleep, Start, Step

CAPTURE_MODES = ("all", "robots", "medium", "none")
LAYOUTS = ("line", "random")
ADDRESSING = ("manual", "auto")


def to_fleet_size(v: object) -> int | tuple[str, ...]:
    """`robots = 4` or `robots = ["a", "b"]`."""
    return to_int(v) if isinstance(v, int) and not isinstance(v, bool) else to_names(v)


def step_ref(index: int, step: Step) -> str:
    return f"step {index} ({step.kind}{f' {step.label!r}' if step.label else ''})"


def reference(steps: Sequence[Step], index: int, ref: str | None) -> int:
    """The step (1-based) that `ref` (a label or a kind; None: the last action step) names,
    looking back from step `index`."""
    earlier = list(enumerate(steps[: index - 1], 1))
    if ref is None:
        found = [i for i, s in earlier if not isinstance(s, Check)]
        if not found:
            raise Bad("no action step before it")
        return found[-1]
    labelled = [i for i, s in earlier if s.label == ref]
    if labelled:
        return labelled[-1]
    kinds = [i for i, s in earlier if s.kind == ref]
    if kinds:
        return kinds[-1]
    raise Bad(f"no earlier step labelled (or of kind) {ref!r}")


def refers(steps: Sequence[Step], index: int, name: str, ref: str | None) -> int:
    try:
        return reference(steps, index, ref)
    except Bad as exc:
        raise Bad(f"{name}: {exc}") from None


@dataclass(frozen=True)
class Scenario:
    """A fleet and the timeline it goes through; validated when made (ScenarioError).

    robots: how many (named r1..rN), or their names.  beacon: sdfrd's beacon interval in
    seconds (the product's is 10; short ones keep runs fast, and deadlines written in beacons
    scale with it).  The medium is a unit disc of `radius` metres; robots stand on a line
    `spacing` metres apart (`layout="line"`) or at seeded random points of `area`
    (`"random"`), unless `positions` says where.  `sdfrd`: more sdfrd options for every
    start.  `capture`: tcpdump on "all" (robots and medium), "robots", "medium" or "none".
    `sample`: seconds between the observer's samples.  `addressing`: "manual" (the lab gives
    each robot a static address) or "auto" (sdfrd derives its own from the MAC, checks and
    defends it: ``sdfrd --addressing auto``; what makes a `Collision` collide).  `runtime`:
    robots as "namespace"s or "docker" containers of the robot image (`netlab.robots`);
    `kinds` gives some robots another (robot -> runtime: a lab may mix them).  `medium`:
    "wired" (a bridge) or "radio" (802.11 radios, each robot's sdfrd joining the fleet's
    WiFi; the VM tier: `make test-radio`).  `air_medium`: a radio lab's medium, "netlab"
    (netlab's own: ranges, moves and partitions) or "hwsim" (the kernel's: all hear all).
    `hosts`: a lab across machines (`netlab.spanlab`): each host (an ssh destination) with
    the robots or groups it runs; the robots no host names are spread over the hosts.
    """

    name: str
    robots: int | Sequence[str] = field(default=3, metadata=toml(to_fleet_size))
    beacon: float = 1.0
    steps: Sequence[Step] = ()
    description: str = ""
    seed: int = 0
    fleet: int = 1
    radius: float = 50.0
    area: tuple[float, float] = HALL
    layout: str = "line"
    spacing: float = 1.0
    positions: Mapping[str, Pos] = field(default_factory=dict)
    groups: Mapping[str, Sequence[str]] = field(default_factory=dict)
    sdfrd: Mapping[str, Any] = field(default_factory=dict)
    capture: str = "all"
    sample: float = 0.25
    addressing: str = "manual"
    runtime: str = "namespace"
    kinds: Mapping[str, str] = field(default_factory=dict)
    medium: str = "wired"
    air_medium: str = "netlab"
    hosts: Mapping[str, Sequence[str]] = field(default_factory=dict)
    #: Where it was read from, for messages.
    source: str | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        try:
            self._validate()
        except Bad as exc:
            raise ScenarioError(f"{self._where()}: {exc}") from None

    def _where(self) -> str:
        name = self.name if isinstance(self.name, str) else "?"
        return self.source or f"scenario {name!r}"

    @property
    def names(self) -> tuple[str, ...]:
        if isinstance(self.robots, int):
            return tuple(f"r{i}" for i in range(1, self.robots + 1))
        return tuple(self.robots)

    def selectors(self) -> Selectors:
        """Its robots and groups, which a step's robot selectors name."""
        return Selectors(self.names, {g: tuple(m) for g, m in self.groups.items()})

    def _validate(self) -> None:
        if not isinstance(self.name, str) or not re.fullmatch(
            r"[A-Za-z0-9][\w.-]{0,63}", self.name
        ):
            raise Bad(f"name: 1-64 of letters, digits, '.', '_' and '-', got {self.name!r}")
        if isinstance(self.robots, bool):
            raise Bad(f"robots: expected a number or a list of names, got {self.robots!r}")
        if isinstance(self.robots, int):
            if not 1 <= self.robots <= naming.MAX_ROBOTS:
                raise Bad(f"robots: must be 1-{naming.MAX_ROBOTS}, got {self.robots}")
        else:
            if isinstance(self.robots, str) or not self.robots:
                raise Bad(f"robots: expected a number or a list of names, got {self.robots!r}")
            for r in self.robots:
                try:
                    naming.check_robot_name(r if isinstance(r, str) else repr(r))
                except NetlabError as exc:
                    raise Bad(f"robots: {exc}") from None
                if r in KEYWORDS:
                    raise Bad(f"robots: {r!r} is a keyword of selectors, not a robot name")
            if len(set(self.robots)) != len(self.robots):
                raise Bad(f"robots: names repeat: {list(self.robots)}")
        bounded(self.beacon, "beacon", 0.01)
        for name in ("seed", "fleet"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise Bad(f"{name}: expected a whole number, got {value!r}")
        if not 0 <= self.fleet <= 255:
            raise Bad(f"fleet: must be 0-255, got {self.fleet}")
        bounded(self.radius, "radius", 0.0)
        area_size(self.area, "area")
        if self.layout not in LAYOUTS:
            raise Bad(f"layout: one of {', '.join(LAYOUTS)}, got {self.layout!r}")
        bounded(self.spacing, "spacing", 0.0)
        if self.addressing not in ADDRESSING:
            raise Bad(f"addressing: one of {', '.join(ADDRESSING)}, got {self.addressing!r}")
        if self.runtime not in RUNTIMES:
            raise Bad(f"runtime: one of {', '.join(RUNTIMES)}, got {self.runtime!r}")
        if self.medium not in AIRS:
            raise Bad(f"medium: one of {', '.join(AIRS)}, got {self.medium!r}")
        if self.air_medium not in AIR_MEDIA:
            raise Bad(f"air_medium: one of {', '.join(AIR_MEDIA)}, got {self.air_medium!r}")
        for robot, kind in self.kinds.items():
            if robot not in self.names:
                raise Bad(f"kinds: unknown robot {robot!r}")
            if kind not in RUNTIMES:
                raise Bad(f"kinds: {robot}: one of {', '.join(RUNTIMES)}, got {kind!r}")
        if self.capture not in CAPTURE_MODES:
            raise Bad(f"capture: one of {', '.join(CAPTURE_MODES)}, got {self.capture!r}")
        bounded(self.sample, "sample", 0.02, 60.0)
        if not isinstance(self.description, str):
            raise Bad(f"description: expected text, got {self.description!r}")
        names = self.names
        for robot, pos in self.positions.items():
            if robot not in names:
                raise Bad(f"positions: unknown robot {robot!r}")
            if not (isinstance(pos, Sequence) and len(pos) == 2):
                raise Bad(f"positions: {robot}: expected (x, y) in metres, got {pos!r}")
            bounded(pos[0], f"positions: {robot}", -1e6, 1e6)
            bounded(pos[1], f"positions: {robot}", -1e6, 1e6)
        for group, members in self.groups.items():
            if group in names or group in KEYWORDS:
                raise Bad(f"groups: {group!r} is a robot name or a keyword; name it otherwise")
            if isinstance(members, str) or not members:
                raise Bad(f"groups: {group}: expected a list of robot names, got {members!r}")
            for m in members:
                if m not in names:
                    raise Bad(f"groups: {group}: unknown robot {m!r}")
        check_field("sdfrd", lambda: check_options(self.sdfrd))
        selectors = self.selectors()
        self._check_hosts(selectors)
        labels: set[str] = set()
        colliding: set[str] = set()
        for i, step in enumerate(self.steps, 1):
            where = step_ref(i, step) if isinstance(step, Step) else f"step {i}"
            try:
                if not isinstance(step, Step):
                    raise Bad(f"expected a Step (Start(), Check(...), ...), got {step!r}")
                if step.label is not None:
                    if not isinstance(step.label, str) or not step.label:
                        raise Bad(f"label: expected a non-empty string, got {step.label!r}")
                    if step.label in labels:
                        raise Bad(f"label: {step.label!r} is already the label of a step")
                    labels.add(step.label)
                step._validate(selectors)
                if isinstance(step, Check):
                    for name in step.condition.refers_to:
                        refers(self.steps, i, name, getattr(step.condition, name))
                if isinstance(step, Collision):
                    if colliding & set(step.robots):
                        raise Bad(
                            f"robots: {fmt_set(colliding & set(step.robots))} already in "
                            "another collision; put them in one step"
                        )
                    colliding |= set(step.robots)
            except Bad as exc:
                raise Bad(f"{where}: {exc}") from None

    def _check_hosts(self, selectors: Selectors) -> None:
        placed: dict[str, str] = {}
        for host, sel in self.hosts.items():
            if not isinstance(host, str) or not DESTINATION_RE.fullmatch(host):
                raise Bad(
                    f"hosts: {host!r} is not an ssh destination (an alias of the ssh "
                    "configuration, or user@address)"
                )
            if isinstance(sel, str) or not isinstance(sel, Sequence):
                raise Bad(f"hosts: {host}: expected a list of robots or groups, got {sel!r}")
            if not sel:
                continue  # it takes its share of the robots no host names
            try:
                robots = selectors.robots(tuple(sel))
            except Bad as exc:
                raise Bad(f"hosts: {host}: {exc}") from None
            for robot in robots:
                if robot in placed:
                    raise Bad(f"hosts: {robot} is on {placed[robot]} and on {host}: one host each")
                placed[robot] = host

    def placement(self) -> dict[str, str]:
        """The robots `hosts` places, and where (robot -> host)."""
        selectors = self.selectors()
        return {r: h for h, sel in self.hosts.items() if sel for r in selectors.robots(tuple(sel))}

    def initial_positions(self) -> dict[str, Pos]:
        names = self.names
        if self.layout == "random":
            rng = random.Random(f"netlab-layout:{self.seed}")
            out = {n: (rng.uniform(0, self.area[0]), rng.uniform(0, self.area[1])) for n in names}
        else:
            out = {n: (i * self.spacing, 0.0) for i, n in enumerate(names)}
        out.update({n: (float(p[0]), float(p[1])) for n, p in self.positions.items()})
        return out

    def runtime_of(self, robot: str) -> str:
        return self.kinds.get(robot, self.runtime)

    def timeline(self, quick: bool = False) -> tuple[float, float]:
        """Seconds the steps take at least (sleeps, mobility, checks that must hold for a
        while) and at most (every check then waiting out its deadline); starting daemons and
        the other actions add seconds to both."""
        least = most = 0.0
        for step in self.steps:
            if isinstance(step, Sleep | Mobility):
                span = step.quick if quick and step.quick is not None else step.duration
                least += seconds(span, self.beacon)
                most += seconds(span, self.beacon)
            elif isinstance(step, Check):
                held = seconds(step.during, self.beacon) if step.during is not None else 0.0
                held += seconds(step.steady, self.beacon) if step.steady is not None else 0.0
                least += held
                most += held + (seconds(step.within, self.beacon) if step.within else 0.0)
        return least, most

    def sdfrd_options(self) -> set[str]:
        """Every sdfrd option a run of this scenario passes."""
        opts = {"beacon_interval", *self.sdfrd}
        if self.addressing != "manual":
            opts.add("addressing")
        for step in self.steps:
            if isinstance(step, Start):
                opts |= set(step.options)
        return opts

    def collisions(self) -> list[tuple[str, ...]]:
        return [tuple(s.robots) for s in self.steps if isinstance(s, Collision)]
