"""Steps: the actions of a scenario's timeline, and the checks between them.

A step is a frozen dataclass with a `kind` (its action key in scenario files; its first
field is that key's value), its fields (the file's other keys, with their defaults) and
`_validate()`.  How the engine carries it out lives in `netlab.scenario.actions`,
registered under the same class; a new step is a class here, added to `STEPS`, and its
function there.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar

from netlab.errors import NetlabError
from netlab.ranges import Pos
from netlab.scenario.conditions import Condition
from netlab.scenario.spec import (
    Bad,
    Duration,
    Robots,
    Selectors,
    Span,
    Spread,
    area_size,
    boolean,
    bounded,
    check_field,
    check_options,
    min_max,
    pairs_of,
    select_groups,
    to_loss,
    to_range,
    toml,
)


@dataclass(frozen=True)
class Step:
    """One step of a scenario's timeline; `label` names it (for `over`/`after` and messages)."""

    kind: ClassVar[str] = "step"
    label: str | None = field(default=None, kw_only=True)

    def _validate(self, selectors: Selectors) -> None:
        pass


@dataclass(frozen=True)
class Start(Step):
    """Start sdfrd on `robots` (all at once), with the scenario's beacon and sdfrd options
    plus `options` (sdfrd flags without dashes: ``{"miss_limit": 3}``); wait until healthy,
    for at most `within` (default: 60 s, or 2 s a robot if more; a radio robot joins the
    fleet's WiFi before it is healthy, slow in an emulated VM)."""

    robots: Robots = "all"
    options: Mapping[str, Any] = field(default_factory=dict)
    within: Span | None = None
    kind: ClassVar[str] = "start"

    def _validate(self, selectors: Selectors) -> None:
        check_field("robots", lambda: selectors.robots(self.robots))
        check_field("options", lambda: check_options(self.options))
        if self.within is not None:
            check_field("within", lambda: Duration.of(self.within or 0))


@dataclass(frozen=True)
class Stop(Step):
    """Stop sdfrd gracefully (SIGTERM: it says Byebye)."""

    robots: Robots
    kind: ClassVar[str] = "stop"

    def _validate(self, selectors: Selectors) -> None:
        check_field("robots", lambda: selectors.robots(self.robots))


@dataclass(frozen=True)
class Kill(Step):
    """kill -9 sdfrd: a silent departure, no Byebye."""

    robots: Robots
    kind: ClassVar[str] = "kill"

    def _validate(self, selectors: Selectors) -> None:
        check_field("robots", lambda: selectors.robots(self.robots))


@dataclass(frozen=True)
class Restart(Step):
    """Stop (SIGTERM; `hard`: kill -9) and start again on the same state directory."""

    robots: Robots
    hard: bool = False
    kind: ClassVar[str] = "restart"

    def _validate(self, selectors: Selectors) -> None:
        check_field("robots", lambda: selectors.robots(self.robots))
        check_field("hard", lambda: boolean(self.hard))


@dataclass(frozen=True)
class Partition(Step):
    """Cut every link between `groups` (robots in none form one more group)."""

    groups: Sequence[Robots]
    kind: ClassVar[str] = "partition"

    def _validate(self, selectors: Selectors) -> None:
        check_field("groups", lambda: select_groups(selectors, self.groups))


@dataclass(frozen=True)
class Merge(Step):
    """End the partition."""

    kind: ClassVar[str] = "merge"


@dataclass(frozen=True)
class Move(Step):
    """Put `robot` at `to` (x, y metres); the range model decides whom it hears."""

    robot: str
    to: Pos
    kind: ClassVar[str] = "move"

    def _validate(self, selectors: Selectors) -> None:
        check_field("robot", lambda: selectors.robot(self.robot))
        if not (isinstance(self.to, Sequence) and len(self.to) == 2):
            raise Bad(f"to: expected (x, y) in metres, got {self.to!r}")
        bounded(self.to[0], "to", -1e6, 1e6)
        bounded(self.to[1], "to", -1e6, 1e6)


@dataclass(frozen=True)
class Mobility(Step):
    """Random waypoint for `duration` (`quick` instead with --quick): each of `robots` walks
    from where it stands to uniform points of `area` (default the scenario's, the paper's
    200 m² hall) at `speed` m/s, pausing `pause` s; positions are applied every `tick` s.
    Seeded (`seed`, default the scenario's): the same run moves the same way."""

    robots: Robots = "all"
    duration: Span = "2 min"
    quick: Span | None = None
    speed: tuple[float, float] = field(default=(0.5, 1.5), metadata=toml(to_range))
    pause: tuple[float, float] = field(default=(0.0, 2.0), metadata=toml(to_range))
    area: tuple[float, float] | None = None
    seed: int | None = None
    tick: float = 0.5
    kind: ClassVar[str] = "mobility"

    def _validate(self, selectors: Selectors) -> None:
        check_field("robots", lambda: selectors.robots(self.robots))
        check_field("duration", lambda: Duration.of(self.duration))
        if self.quick is not None:
            check_field("quick", lambda: Duration.of(self.quick or 0))
        min_max(self.speed, "speed", 0.0)
        if not self.speed[0] > 0:
            raise Bad(f"speed: the minimum must be above 0 m/s, got {self.speed[0]!r}")
        min_max(self.pause, "pause", 0.0)
        if self.area is not None:
            area_size(self.area, "area")
        if self.seed is not None and (
            isinstance(self.seed, bool) or not isinstance(self.seed, int)
        ):
            raise Bad(f"seed: expected a whole number, got {self.seed!r}")
        bounded(self.tick, "tick", 0.01, 60.0)


@dataclass(frozen=True)
class Quality(Step):
    """Loss in % on every pair from `robots` to `peers` (default: every pair within `robots`),
    both ways if `both`, while linked; `loss=None` gives the pairs back to the range model."""

    robots: Robots
    peers: Robots | None = None
    loss: float | None = field(default=0.0, metadata=toml(to_loss))
    both: bool = True
    kind: ClassVar[str] = "quality"

    def _validate(self, selectors: Selectors) -> None:
        check_field("robots", lambda: selectors.robots(self.robots))
        if self.peers is not None:
            check_field("peers", lambda: selectors.robots(self.peers or ()))
        if self.loss is not None:
            bounded(self.loss, "loss", 0.0, 100.0)
        check_field("both", lambda: boolean(self.both))
        robots = selectors.robots(self.robots)
        if not pairs_of(robots, selectors.robots(self.peers or self.robots), both=False):
            raise Bad("names no pair of two different robots")


def _shape_params() -> list[str]:
    from netlab.shaping import LinkShape  # late: it loads pyroute2

    return [f.name for f in fields(LinkShape)]


@dataclass(frozen=True)
class Shape(Step):
    """Shape each robot's link (`netlab.shaping.LinkShape` parameters: delay, jitter, loss,
    duplicate, reorder, corrupt, rate); no parameters removes all shaping."""

    robots: Robots
    params: Mapping[str, Any] = field(default_factory=dict, metadata=toml(Spread(_shape_params)))
    kind: ClassVar[str] = "shape"

    def _validate(self, selectors: Selectors) -> None:
        from netlab.shaping import LinkShape  # late: it loads pyroute2

        check_field("robots", lambda: selectors.robots(self.robots))
        try:
            LinkShape.of(**dict(self.params))
        except (NetlabError, TypeError, ValueError) as exc:
            raise Bad(str(exc)) from None


@dataclass(frozen=True)
class Publish(Step):
    """Publish a service named `service` on each robot (through its REST API)."""

    robots: Robots
    service: str
    type: str
    url: str | None = None
    attributes: Mapping[str, Any] = field(default_factory=dict)
    kind: ClassVar[str] = "publish"

    def _validate(self, selectors: Selectors) -> None:
        check_field("robots", lambda: selectors.robots(self.robots))
        for name in ("service", "type"):
            value = getattr(self, name)
            if not isinstance(value, str) or not value:
                raise Bad(f"{name}: expected a non-empty string, got {value!r}")
        if self.url is not None and not isinstance(self.url, str):
            raise Bad(f"url: expected a string, got {self.url!r}")
        if not isinstance(self.attributes, Mapping):
            raise Bad(f"attributes: expected a table, got {self.attributes!r}")
        for key, value in self.attributes.items():
            if not isinstance(value, str | int | float | bool):
                raise Bad(f"attributes: {key}: expected a string, number or boolean")


@dataclass(frozen=True)
class Unpublish(Step):
    """Withdraw the service named `service` that a Publish step put on each robot."""

    robots: Robots
    service: str
    kind: ClassVar[str] = "unpublish"

    def _validate(self, selectors: Selectors) -> None:
        check_field("robots", lambda: selectors.robots(self.robots))
        if not isinstance(self.service, str) or not self.service:
            raise Bad(f"service: expected a non-empty string, got {self.service!r}")


def twin_mac(mac: str, k: int) -> str:
    """A different MAC with the same last two octets: the same first derived address
    (`sdfr.protocol.addressing.candidates`), yet ARP can tell the two robots apart."""
    octets = mac.split(":")
    octets[1] = f"{(int(octets[1], 16) + k) % 256:02x}"
    return ":".join(octets)


@dataclass(frozen=True)
class Collision(Step):
    """Give `robots` MACs ending alike, so that they derive the same SDfR address.

    Applied when the lab is made, wherever the step stands.  It only makes the addresses
    collide with sdfrd's address self-configuration (``--addressing auto``, set through
    the scenario's ``[sdfrd]`` options); the lab's own static addresses stay distinct.
    """

    robots: Sequence[str]
    kind: ClassVar[str] = "collision"

    def _validate(self, selectors: Selectors) -> None:
        if isinstance(self.robots, str) or not isinstance(self.robots, Sequence):
            raise Bad(f"robots: expected a list of robot names, got {self.robots!r}")
        names = [selectors.robot(r) for r in self.robots]
        if len(set(names)) < 2:
            raise Bad(f"robots: needs two or more different robots, got {list(self.robots)}")


@dataclass(frozen=True)
class Sleep(Step):
    """Let time pass (`quick` instead with --quick)."""

    duration: Span
    quick: Span | None = None
    kind: ClassVar[str] = "sleep"

    def _validate(self, selectors: Selectors) -> None:
        check_field("duration", lambda: Duration.of(self.duration))
        if self.quick is not None:
            check_field("quick", lambda: Duration.of(self.quick or 0))


@dataclass(frozen=True)
class Check(Step):
    """Wait up to `within` for `condition` to hold, and (`during`) for it to keep holding.
    With `steady`, it counts as holding only once it has held that long without a break (a
    break starts the count again); the stretch must begin within `within`.

    A failed check is recorded and the run goes on.
    """

    condition: Condition
    within: Span | None = None
    during: Span | None = None
    steady: Span | None = None
    kind: ClassVar[str] = "check"
    #: A failure ends the run.
    fatal: ClassVar[bool] = False

    def describe(self) -> str:
        return self.label or self.condition.describe()

    def _validate(self, selectors: Selectors) -> None:
        if not isinstance(self.condition, Condition):
            raise Bad(f"condition: expected a Condition (Lists(), ...), got {self.condition!r}")
        spans = (("within", self.within), ("during", self.during), ("steady", self.steady))
        for name, value in spans:
            if value is not None:
                try:
                    Duration.of(value)
                except Bad as exc:
                    raise Bad(f"{name}: {exc}") from None
        timed = self.within is not None or self.during is not None
        if self.condition.polled and not timed:
            raise Bad(f"a {self.condition.kind} check needs within (a deadline) or during")
        if not self.condition.polled and (timed or self.steady is not None):
            raise Bad(f"a {self.condition.kind} check is judged once: no within, during or steady")
        if self.steady is not None and self.within is None:
            raise Bad("steady needs within: the deadline for the steady stretch to begin")
        self.condition._validate(selectors)


@dataclass(frozen=True)
class Wait(Check):
    """A `Check` whose failure ends the run: later steps rely on it."""

    kind: ClassVar[str] = "wait"
    fatal: ClassVar[bool] = True


STEPS: dict[str, type[Step]] = {
    s.kind: s
    for s in (
        Start,
        Stop,
        Kill,
        Restart,
        Partition,
        Merge,
        Move,
        Mobility,
        Quality,
        Shape,
        Publish,
        Unpublish,
        Collision,
        Sleep,
        Wait,
        Check,
    )
}
