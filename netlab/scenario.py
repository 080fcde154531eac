"""Scenarios: a timeline of steps and checks, run against a real `netlab.lab.Lab`.

In Python (tests)::

    sc = Scenario(
        "split", robots=4, beacon=0.5, groups={"a": ["r1", "r2"], "b": ["r3", "r4"]},
        steps=[
            Start(),
            Publish("all", "camera", "sensor.camera"),
            Wait(Lists(), within="2 s"),
            Partition(["a", "b"], label="split"),
            Check(Lists(groups=["a", "b"]), within="3 beacons"),
            Merge(label="merge"),
            Check(Lists(), within="1 beacon + 1 s"),
        ],
    )
    result = run(sc, runs=Path("runs"))      # RunResult: .ok, .checks, .run_dir

or as a TOML file (`load(path)`, ``netlab run FILE``); the bundled ones are in
``netlab/scenarios/`` (`bundled()`, ``netlab run NAME``) and show the format::

    [scenario]
    name = "split"
    robots = 4            # r1..r4, or a list of names
    beacon = 0.5          # seconds; the product default is 10
    [groups]
    a = ["r1", "r2"]
    [[step]]
    start = "all"
    [[step]]
    check = "lists"       # a condition; `wait` instead of `check` stops the run on failure
    groups = ["a", "b"]
    within = "3 beacons"  # or 1.5, "1.5 s", "500 ms", "1 beacon + 1 s"

Each ``[[step]]`` has one action key, whose value is its main argument; its other keys are
that step's fields (the step classes below name them).  Robots are selected by name, by group
name, ``"all"`` or ``"running"`` (those whose daemon the scenario started and has not stopped),
or a list of these.

Steps run one after the other.  A check polls its condition until it holds, up to a deadline
(`within`) counted from the end of the last action step before it, so consecutive checks of one
event share that event's clock; `during` makes it hold for that long too.  A failed `check` is
recorded and the run goes on; a failed `wait` ends the run (later steps rely on it).  Checks
consider the robots whose daemons run: a stopped robot is listed by nobody and lists nobody.

During a run: tcpdump on every robot and on the medium (``capture``), an `Observer` sampling
the neighbour lists against the medium's truth, progress lines, and at the end ``run.json``
(samples and check results), ``report.json`` and the plots of `netlab.report` in the run folder,
with the pcaps and each daemon's log (``logs/``) kept for inspection.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import math
import os
import random
import re
import shutil
import subprocess
import sys
import time
import tomllib
from collections.abc import Callable, Iterable, Mapping, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass, field, replace
from datetime import datetime
from functools import cache
from pathlib import Path
from typing import Any, ClassVar, Protocol

from netlab import naming, procstat
from netlab.analysis import count_updates, natural_order, read_run
from netlab.errors import NetlabError
from netlab.mobility import HALL, RandomWaypoint
from netlab.observe import (
    ClientLike,
    Observer,
    Probe,
    Sample,
    TruthLog,
    TruthState,
    address_problems,
    agreement,
    connectivity,
    expect_problems,
    flaps,
    fmt_set,
    history_problems,
    indicator_problems,
    indicators_before,
    unreachable_problems,
)
from netlab.ranges import Pos, RangeModel, UnitDisc
from sdfr.errors import ApiError

__all__ = [
    "BUNDLED_DIR",
    "Agreement",
    "Backend",
    "Check",
    "CheckResult",
    "Collision",
    "Condition",
    "DistinctAddresses",
    "Duration",
    "Flaps",
    "InHistory",
    "Indicator",
    "Kill",
    "LabLike",
    "LabSpec",
    "Lists",
    "Medium",
    "Merge",
    "Mobility",
    "Move",
    "Partition",
    "Publish",
    "Quality",
    "Resources",
    "Restart",
    "RunResult",
    "Scenario",
    "ScenarioError",
    "Shape",
    "Sleep",
    "Start",
    "Step",
    "StepError",
    "Stop",
    "Unpublish",
    "Unreachable",
    "Updates",
    "Wait",
    "bundled",
    "default_lab_name",
    "find",
    "from_dict",
    "load",
    "loads",
    "missing_requirements",
    "rebuild_report",
    "run",
    "sdfrd_flags",
]

BUNDLED_DIR = Path(__file__).with_name("scenarios")
RUN_JSON = "run.json"
RUN_SCHEMA = "netlab-scenario-run/1"
PRODUCT_BEACON = 10.0
CAPTURE_MODES = ("all", "robots", "medium", "none")
LAYOUTS = ("line", "random")
#: Names a selector may use besides robots and groups.
KEYWORDS = ("all", "running")
#: sdfrd options the lab sets itself.
RESERVED_OPTIONS = ("iface", "fleet", "robot_id", "state_dir", "beacon_interval", "addressing")
ADDRESSING = ("manual", "auto")


class ScenarioError(NetlabError, ValueError):
    """A scenario (file or objects) is not valid; the message names the step and the field."""


class StepError(NetlabError):
    """A step could not be carried out on this lab."""


class _Bad(ValueError):
    """A field's value is wrong; re-raised as ScenarioError once we know where it is."""


# ---------------------------------------------------------------------------------------------
# Durations: seconds, or beacon periods


_TERM_RE = re.compile(
    r"^\s*(\d+(?:\.\d*)?|\.\d+)\s*"
    r"(ms|s|sec|secs|seconds?|min|mins|minutes?|beacons?)?\s*$",
    re.IGNORECASE,
)
_UNIT_SECONDS = {"ms": 0.001, "s": 1.0, "sec": 1.0, "secs": 1.0, "second": 1.0, "seconds": 1.0}
_UNIT_SECONDS |= {"min": 60.0, "mins": 60.0, "minute": 60.0, "minutes": 60.0}


@dataclass(frozen=True, slots=True)
class Duration:
    """`seconds` plus `beacons` beacon periods: deadlines that scale with the beacon."""

    seconds: float = 0.0
    beacons: float = 0.0

    @classmethod
    def of(cls, value: Span) -> Duration:
        """From a Duration, a number of seconds, or text: "2 s", "500 ms", "3 beacons",
        "2 min", "1 beacon + 1 s"; ValueError saying what is accepted otherwise."""
        if isinstance(value, Duration):
            return value
        if isinstance(value, bool) or not isinstance(value, int | float | str):
            raise _Bad(f"expected seconds or text like '3 beacons', got {value!r}")
        if not isinstance(value, str):
            seconds = float(value)
            if not (math.isfinite(seconds) and seconds >= 0):
                raise _Bad(f"must be a finite number of seconds >= 0, got {value!r}")
            return cls(seconds)
        secs = beacons = 0.0
        for term in value.split("+"):
            m = _TERM_RE.match(term)
            if m is None:
                raise _Bad(
                    f"cannot read {value!r} as a duration: write e.g. 2, '2 s', '500 ms', "
                    "'2 min', '3 beacons' or '1 beacon + 1 s'"
                )
            number, unit = float(m.group(1)), (m.group(2) or "s").lower()
            if unit.startswith("beacon"):
                beacons += number
            else:
                secs += number * _UNIT_SECONDS[unit]
        return cls(secs, beacons)

    def at(self, beacon: float) -> float:
        """In seconds, with this beacon period."""
        return self.seconds + self.beacons * beacon

    def __str__(self) -> str:
        parts = []
        if self.beacons:
            parts.append(f"{self.beacons:g} beacon{'' if self.beacons == 1 else 's'}")
        if self.seconds or not parts:
            parts.append(f"{self.seconds:g} s")
        return " + ".join(parts)


Span = Duration | float | int | str
Robots = str | Sequence[str]


def seconds(value: Span, beacon: float) -> float:
    """`value` in seconds with this beacon period."""
    return Duration.of(value).at(beacon)


# ---------------------------------------------------------------------------------------------
# Robot selectors


@dataclass(frozen=True, slots=True)
class _Ctx:
    """What a scenario's steps are checked against: its robots and groups."""

    names: tuple[str, ...]
    groups: Mapping[str, tuple[str, ...]]

    def robots(self, sel: Robots, running: Iterable[str] | None = None) -> tuple[str, ...]:
        """The robots `sel` names, in order; "running" is every robot when `running` is None."""
        items = [sel] if isinstance(sel, str) else list(sel)
        if not items:
            raise _Bad("names no robot (an empty list)")
        out: list[str] = []
        for item in items:
            if not isinstance(item, str):
                raise _Bad(f"expected robot or group names, got {item!r}")
            if item == "all":
                out.extend(self.names)
            elif item == "running":
                alive = set(self.names if running is None else running)
                out.extend(n for n in self.names if n in alive)
            elif item in self.groups:
                out.extend(self.groups[item])
            elif item in self.names:
                out.append(item)
            else:
                groups = f"; groups: {', '.join(self.groups)}" if self.groups else ""
                raise _Bad(
                    f"unknown robot or group {item!r} (robots: {_names_text(self.names)}"
                    f"{groups}; or 'all', 'running')"
                )
        return tuple(dict.fromkeys(out))

    def robot(self, name: str) -> str:
        if not isinstance(name, str) or name not in self.names:
            raise _Bad(f"unknown robot {name!r} (robots: {_names_text(self.names)})")
        return name


def _names_text(names: Sequence[str]) -> str:
    """``r1..r6`` for a default fleet, else the names."""
    if len(names) > 2 and list(names) == [f"r{i}" for i in range(1, len(names) + 1)]:
        return f"r1..r{len(names)}"
    return ", ".join(names)


def _sel_text(sel: Robots | None, default: str = "every robot") -> str:
    if sel is None:
        return default
    if isinstance(sel, str):
        return {"all": "all robots", "running": "all running robots"}.get(sel, sel)
    return fmt_set(sel)


def _check_field(name: str, check: Callable[[], object]) -> None:
    try:
        check()
    except _Bad as exc:
        raise _Bad(f"{name}: {exc}") from None


def _number(value: object, what: str, low: float = -math.inf, high: float = math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise _Bad(f"{what}: expected a number, got {value!r}")
    if not (math.isfinite(value) and low <= value <= high):
        rng = f">= {low:g}" if high == math.inf else f"{low:g}-{high:g}"
        raise _Bad(f"{what}: must be {rng}, got {value!r}")
    return float(value)


def _min_max(value: object, what: str, low: float) -> None:
    if not (isinstance(value, Sequence) and len(value) == 2):
        raise _Bad(f"{what}: expected (min, max), got {value!r}")
    a = _number(value[0], what, low)
    b = _number(value[1], what, low)
    if a > b:
        raise _Bad(f"{what}: min {a:g} is above max {b:g}")


def _count(value: object, what: str) -> None:
    if isinstance(value, bool) or not isinstance(value, int):
        raise _Bad(f"{what}: expected a whole number, got {value!r}")
    if value < 0:
        raise _Bad(f"{what}: must be >= 0, got {value}")


def _size(value: object, what: str) -> None:
    if not (isinstance(value, Sequence) and len(value) == 2):
        raise _Bad(f"{what}: expected (width, height) in metres, got {value!r}")
    _number(value[0], what, 0.001)
    _number(value[1], what, 0.001)


# ---------------------------------------------------------------------------------------------
# Conditions: what a check waits for


@dataclass(frozen=True)
class Condition:
    """What a `Check` looks at."""

    kind: ClassVar[str] = "condition"
    #: Polled until it holds (False: judged once over data already gathered).
    polled: ClassVar[bool] = True

    def describe(self) -> str:
        return self.kind

    def _validate(self, ctx: _Ctx) -> None:
        pass


@dataclass(frozen=True)
class Lists(Condition):
    """Each running robot of a group lists every other running robot of that group as
    reachable (`exact`: and nobody else), each once, and (`services`) with exactly the services
    the scenario published on it.  `robots`: one group (default "running"); `groups`: several.
    """

    robots: Robots | None = None
    groups: Sequence[Robots] | None = None
    services: bool = True
    exact: bool = True
    kind: ClassVar[str] = "lists"

    def describe(self) -> str:
        tail = (", with services" if self.services else "") + ("" if self.exact else " (at least)")
        if self.groups is not None:
            parts = " | ".join(_sel_text(g) for g in self.groups)
            return f"{parts}: each lists {'only ' if self.exact else ''}its group{tail}"
        who = _sel_text(self.robots, "all running robots")
        return f"{who} list each other{tail}"

    def _validate(self, ctx: _Ctx) -> None:
        if self.robots is not None and self.groups is not None:
            raise _Bad("give robots (one group) or groups (several), not both")
        if self.robots is not None:
            _check_field("robots", lambda: ctx.robots(self.robots or ()))
        if self.groups is not None:
            _check_field("groups", lambda: _groups(ctx, self.groups or ()))
        _check_field("services", lambda: _boolean(self.services))
        _check_field("exact", lambda: _boolean(self.exact))


@dataclass(frozen=True)
class Medium(Condition):
    """Each running robot of `robots` lists as reachable exactly the running robots the medium
    links it to now (the ground truth), with their services if `services`."""

    robots: Robots = "running"
    services: bool = False
    kind: ClassVar[str] = "medium"

    def describe(self) -> str:
        who = _sel_text(self.robots)
        return f"{who} list exactly whom the medium links them to"

    def _validate(self, ctx: _Ctx) -> None:
        _check_field("robots", lambda: ctx.robots(self.robots))
        _check_field("services", lambda: _boolean(self.services))


@dataclass(frozen=True)
class Unreachable(Condition):
    """No robot of `on` (default: every other running robot) lists any of `robots` as
    reachable."""

    robots: Robots
    on: Robots | None = None
    kind: ClassVar[str] = "unreachable"

    def describe(self) -> str:
        return f"{_sel_text(self.robots)} unreachable on {_sel_text(self.on, 'every peer')}"

    def _validate(self, ctx: _Ctx) -> None:
        _check_field("robots", lambda: ctx.robots(self.robots))
        if self.on is not None:
            _check_field("on", lambda: ctx.robots(self.on or ()))


@dataclass(frozen=True)
class InHistory(Condition):
    """Every robot of `on` (default: every other running robot) holds each of `robots` in its
    history map; as reachable or not (`reachable`), with its connection indicator below a
    bound (`indicator_below`), when those are given."""

    robots: Robots
    on: Robots | None = None
    reachable: bool | None = None
    indicator_below: float | None = None
    falling: bool = False
    kind: ClassVar[str] = "history"

    def describe(self) -> str:
        state = {None: "", True: " as reachable", False: " as unreachable"}[self.reachable]
        fell = ", indicator fallen since the last step" if self.falling else ""
        return f"{_sel_text(self.robots)} in the history of {_sel_text(self.on, 'every peer')}" + (
            state + fell
        )

    def _validate(self, ctx: _Ctx) -> None:
        _check_field("robots", lambda: ctx.robots(self.robots))
        if self.on is not None:
            _check_field("on", lambda: ctx.robots(self.on or ()))
        if self.reachable is not None:
            _check_field("reachable", lambda: _boolean(self.reachable))
        if self.indicator_below is not None:
            _number(self.indicator_below, "indicator_below", 0.0, 1.0)
        _check_field("falling", lambda: _boolean(self.falling))


@dataclass(frozen=True)
class DistinctAddresses(Condition):
    """No two robots are listed at the same address by `robots` (an address collision was
    resolved).  Meaningful with sdfrd's address self-configuration (``--addressing auto``)."""

    robots: Robots = "running"
    kind: ClassVar[str] = "addresses"

    def describe(self) -> str:
        return f"{_sel_text(self.robots)}: every robot at its own address"

    def _validate(self, ctx: _Ctx) -> None:
        _check_field("robots", lambda: ctx.robots(self.robots))


MEASURES = ("pairs", "samples")


@dataclass(frozen=True)
class Agreement(Condition):
    """The sampled neighbour lists agree with the medium's truth, within `lag`, over the window
    of step `over` (a label or a step kind; default: the last action step): share of
    (sample, robot, peer) observations (`measure="pairs"`) or of samples where every list
    agrees (`"samples"`) at least `at_least`.  `loss_lag` (default `lag`) allows a different
    lag for a link that vanished (sdfrd drops a silent peer after its miss limit, 3 beacon
    periods by default).  Judged once, from the observer's samples."""

    at_least: float = 0.95
    lag: Span = "1 beacon"
    loss_lag: Span | None = None
    over: str | None = None
    measure: str = "pairs"
    kind: ClassVar[str] = "agreement"
    polled: ClassVar[bool] = False

    def describe(self) -> str:
        over = f" over {self.over}" if self.over else ""
        loss = f", {Duration.of(self.loss_lag)} for lost links" if self.loss_lag is not None else ""
        return (
            f"lists agree with the medium >= {self.at_least:.0%} of {self.measure}{over} "
            f"(lag {Duration.of(self.lag)}{loss})"
        )

    def _validate(self, ctx: _Ctx) -> None:
        _number(self.at_least, "at_least", 0.0, 1.0)
        _check_field("lag", lambda: Duration.of(self.lag))
        if self.loss_lag is not None:
            _check_field("loss_lag", lambda: Duration.of(self.loss_lag or 0))
        if self.measure not in MEASURES:
            raise _Bad(f"measure: one of {', '.join(MEASURES)}, got {self.measure!r}")


@dataclass(frozen=True)
class Updates(Condition):
    """At most `at_most` Update datagrams went on the air from the start of step `after` (a
    label or a step kind; default: the last action step) to this check: services are not
    re-fetched when unchanged.  Counted from the captures at the end of the run."""

    at_most: int = 0
    after: str | None = None
    kind: ClassVar[str] = "updates"
    polled: ClassVar[bool] = False

    def describe(self) -> str:
        return f"at most {self.at_most} Update datagrams since {self.after or 'the last step'}"

    def _validate(self, ctx: _Ctx) -> None:
        _count(self.at_most, "at_most")


@dataclass(frozen=True)
class Flaps(Condition):
    """No robot drops a peer the medium keeps linked more than `at_most` times within any `per`
    (a flap: listed in one sample of the observer, not in the next), over the window of step
    `over` (a label or a step kind; default: the last action step).  Judged once, from the
    observer's samples, so a flap shorter than the sample period may go unseen."""

    at_most: int = 1
    per: Span = "1 min"
    over: str | None = None
    kind: ClassVar[str] = "flaps"
    polled: ClassVar[bool] = False

    def describe(self) -> str:
        over = f" over {self.over}" if self.over else ""
        return f"no peer flaps out more than {self.at_most} per {Duration.of(self.per)}{over}"

    def _validate(self, ctx: _Ctx) -> None:
        _count(self.at_most, "at_most")
        _check_field("per", lambda: Duration.of(self.per))


@dataclass(frozen=True)
class Indicator(Condition):
    """Each running robot of `robots` rates every peer it lists within `tolerance` (0-1) of
    the share of pings the medium lets come back: (1 - loss there) x (1 - loss back)."""

    robots: Robots = "running"
    tolerance: float = 0.15
    kind: ClassVar[str] = "indicator"

    def describe(self) -> str:
        return (
            f"{_sel_text(self.robots)}: indicators within {self.tolerance * 100:g} points of "
            "the medium's round-trip delivery"
        )

    def _validate(self, ctx: _Ctx) -> None:
        _check_field("robots", lambda: ctx.robots(self.robots))
        _number(self.tolerance, "tolerance", 0.0, 1.0)


@dataclass(frozen=True)
class Resources(Condition):
    """What each daemon (sdfrd and its two layers) used over the window of step `over`: CPU as
    % of one core, and memory (PSS, MiB) at its end; at most `cpu_at_most` / `pss_at_most`
    per daemon when given.  Judged once, from /proc readings at the start and end of that
    step; the numbers go to the report."""

    over: str | None = None
    cpu_at_most: float | None = None
    pss_at_most: float | None = None
    kind: ClassVar[str] = "resources"
    polled: ClassVar[bool] = False

    def describe(self) -> str:
        limits = []
        if self.cpu_at_most is not None:
            limits.append(f"CPU <= {self.cpu_at_most:g} %")
        if self.pss_at_most is not None:
            limits.append(f"PSS <= {self.pss_at_most:g} MiB")
        over = f" over {self.over}" if self.over else ""
        return f"CPU and memory per daemon{over}" + (f": {', '.join(limits)}" if limits else "")

    def _validate(self, ctx: _Ctx) -> None:
        if self.cpu_at_most is not None:
            _number(self.cpu_at_most, "cpu_at_most", 0.0)
        if self.pss_at_most is not None:
            _number(self.pss_at_most, "pss_at_most", 0.0)


CONDITIONS: dict[str, type[Condition]] = {
    c.kind: c
    for c in (
        Lists,
        Medium,
        Unreachable,
        InHistory,
        DistinctAddresses,
        Agreement,
        Updates,
        Flaps,
        Indicator,
        Resources,
    )
}


def _boolean(value: object) -> bool:
    if not isinstance(value, bool):
        raise _Bad(f"expected true or false, got {value!r}")
    return value


def _groups(ctx: _Ctx, groups: Sequence[Robots]) -> list[tuple[str, ...]]:
    if isinstance(groups, str) or not isinstance(groups, Sequence) or not groups:
        raise _Bad(f"expected a list of groups, got {groups!r}")
    out = [ctx.robots(g) for g in groups]
    seen: set[str] = set()
    for g in out:
        if seen & set(g):
            raise _Bad(f"robots in more than one group: {fmt_set(seen & set(g))}")
        seen |= set(g)
    return out


# ---------------------------------------------------------------------------------------------
# Steps


@dataclass(frozen=True)
class Step:
    """One step of a scenario's timeline; `label` names it (for `over`/`after` and messages)."""

    kind: ClassVar[str] = "step"
    label: str | None = field(default=None, kw_only=True)

    def _validate(self, ctx: _Ctx) -> None:
        pass


@dataclass(frozen=True)
class Start(Step):
    """Start sdfrd on `robots` (all at once), with the scenario's beacon and sdfrd options
    plus `options` (sdfrd flags without dashes: ``{"miss_limit": 3}``); wait until healthy."""

    robots: Robots = "all"
    options: Mapping[str, Any] = field(default_factory=dict)
    kind: ClassVar[str] = "start"

    def _validate(self, ctx: _Ctx) -> None:
        _check_field("robots", lambda: ctx.robots(self.robots))
        _check_field("options", lambda: _options(self.options))


@dataclass(frozen=True)
class Stop(Step):
    """Stop sdfrd gracefully (SIGTERM: it says Byebye)."""

    robots: Robots
    kind: ClassVar[str] = "stop"

    def _validate(self, ctx: _Ctx) -> None:
        _check_field("robots", lambda: ctx.robots(self.robots))


@dataclass(frozen=True)
class Kill(Step):
    """kill -9 sdfrd: a silent departure, no Byebye."""

    robots: Robots
    kind: ClassVar[str] = "kill"

    def _validate(self, ctx: _Ctx) -> None:
        _check_field("robots", lambda: ctx.robots(self.robots))


@dataclass(frozen=True)
class Restart(Step):
    """Stop (SIGTERM; `hard`: kill -9) and start again on the same state directory."""

    robots: Robots
    hard: bool = False
    kind: ClassVar[str] = "restart"

    def _validate(self, ctx: _Ctx) -> None:
        _check_field("robots", lambda: ctx.robots(self.robots))
        _check_field("hard", lambda: _boolean(self.hard))


@dataclass(frozen=True)
class Partition(Step):
    """Cut every link between `groups` (robots in none form one more group)."""

    groups: Sequence[Robots]
    kind: ClassVar[str] = "partition"

    def _validate(self, ctx: _Ctx) -> None:
        _check_field("groups", lambda: _groups(ctx, self.groups))


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

    def _validate(self, ctx: _Ctx) -> None:
        _check_field("robot", lambda: ctx.robot(self.robot))
        if not (isinstance(self.to, Sequence) and len(self.to) == 2):
            raise _Bad(f"to: expected (x, y) in metres, got {self.to!r}")
        _number(self.to[0], "to", -1e6, 1e6)
        _number(self.to[1], "to", -1e6, 1e6)


@dataclass(frozen=True)
class Mobility(Step):
    """Random waypoint for `duration` (`quick` instead with --quick): each of `robots` walks
    from where it stands to uniform points of `area` (default the scenario's, the paper's
    200 m² hall) at `speed` m/s, pausing `pause` s; positions are applied every `tick` s.
    Seeded (`seed`, default the scenario's): the same run moves the same way."""

    robots: Robots = "all"
    duration: Span = "2 min"
    quick: Span | None = None
    speed: tuple[float, float] = (0.5, 1.5)
    pause: tuple[float, float] = (0.0, 2.0)
    area: tuple[float, float] | None = None
    seed: int | None = None
    tick: float = 0.5
    kind: ClassVar[str] = "mobility"

    def _validate(self, ctx: _Ctx) -> None:
        _check_field("robots", lambda: ctx.robots(self.robots))
        _check_field("duration", lambda: Duration.of(self.duration))
        if self.quick is not None:
            _check_field("quick", lambda: Duration.of(self.quick or 0))
        _min_max(self.speed, "speed", 0.0)
        if not self.speed[0] > 0:
            raise _Bad(f"speed: the minimum must be above 0 m/s, got {self.speed[0]!r}")
        _min_max(self.pause, "pause", 0.0)
        if self.area is not None:
            _size(self.area, "area")
        if self.seed is not None and (
            isinstance(self.seed, bool) or not isinstance(self.seed, int)
        ):
            raise _Bad(f"seed: expected a whole number, got {self.seed!r}")
        _number(self.tick, "tick", 0.01, 60.0)


@dataclass(frozen=True)
class Quality(Step):
    """Loss in % on every pair from `robots` to `peers` (default: every pair within `robots`),
    both ways if `both`, while linked; `loss=None` gives the pairs back to the range model."""

    robots: Robots
    peers: Robots | None = None
    loss: float | None = 0.0
    both: bool = True
    kind: ClassVar[str] = "quality"

    def _validate(self, ctx: _Ctx) -> None:
        _check_field("robots", lambda: ctx.robots(self.robots))
        if self.peers is not None:
            _check_field("peers", lambda: ctx.robots(self.peers or ()))
        if self.loss is not None:
            _number(self.loss, "loss", 0.0, 100.0)
        _check_field("both", lambda: _boolean(self.both))
        if not _pairs(ctx.robots(self.robots), ctx.robots(self.peers or self.robots), both=False):
            raise _Bad("names no pair of two different robots")


@dataclass(frozen=True)
class Shape(Step):
    """Shape each robot's link (`netlab.shaping.LinkShape` parameters: delay, jitter, loss,
    duplicate, reorder, corrupt, rate); no parameters removes all shaping."""

    robots: Robots
    params: Mapping[str, Any] = field(default_factory=dict)
    kind: ClassVar[str] = "shape"

    def _validate(self, ctx: _Ctx) -> None:
        from netlab.shaping import LinkShape  # late: it loads pyroute2

        _check_field("robots", lambda: ctx.robots(self.robots))
        try:
            LinkShape.of(**dict(self.params))
        except (NetlabError, TypeError, ValueError) as exc:
            raise _Bad(str(exc)) from None


@dataclass(frozen=True)
class Publish(Step):
    """Publish a service named `service` on each robot (through its REST API)."""

    robots: Robots
    service: str
    type: str
    url: str | None = None
    attributes: Mapping[str, Any] = field(default_factory=dict)
    kind: ClassVar[str] = "publish"

    def _validate(self, ctx: _Ctx) -> None:
        _check_field("robots", lambda: ctx.robots(self.robots))
        for name in ("service", "type"):
            value = getattr(self, name)
            if not isinstance(value, str) or not value:
                raise _Bad(f"{name}: expected a non-empty string, got {value!r}")
        if self.url is not None and not isinstance(self.url, str):
            raise _Bad(f"url: expected a string, got {self.url!r}")
        if not isinstance(self.attributes, Mapping):
            raise _Bad(f"attributes: expected a table, got {self.attributes!r}")
        for key, value in self.attributes.items():
            if not isinstance(value, str | int | float | bool):
                raise _Bad(f"attributes: {key}: expected a string, number or boolean")


@dataclass(frozen=True)
class Unpublish(Step):
    """Withdraw the service named `service` that a Publish step put on each robot."""

    robots: Robots
    service: str
    kind: ClassVar[str] = "unpublish"

    def _validate(self, ctx: _Ctx) -> None:
        _check_field("robots", lambda: ctx.robots(self.robots))
        if not isinstance(self.service, str) or not self.service:
            raise _Bad(f"service: expected a non-empty string, got {self.service!r}")


def twin_mac(mac: str, k: int) -> str:
    """A different MAC with the same last two octets: the same first derived address
    (`sdfr.addressing.candidates`), yet ARP can tell the two robots apart."""
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

    def _validate(self, ctx: _Ctx) -> None:
        if isinstance(self.robots, str) or not isinstance(self.robots, Sequence):
            raise _Bad(f"robots: expected a list of robot names, got {self.robots!r}")
        names = [ctx.robot(r) for r in self.robots]
        if len(set(names)) < 2:
            raise _Bad(f"robots: needs two or more different robots, got {list(self.robots)}")


@dataclass(frozen=True)
class Sleep(Step):
    """Let time pass (`quick` instead with --quick)."""

    duration: Span
    quick: Span | None = None
    kind: ClassVar[str] = "sleep"

    def _validate(self, ctx: _Ctx) -> None:
        _check_field("duration", lambda: Duration.of(self.duration))
        if self.quick is not None:
            _check_field("quick", lambda: Duration.of(self.quick or 0))


@dataclass(frozen=True)
class Check(Step):
    """Wait up to `within` for `condition` to hold, and (`during`) for it to keep holding.

    A failed check is recorded and the run goes on.
    """

    condition: Condition
    within: Span | None = None
    during: Span | None = None
    kind: ClassVar[str] = "check"
    #: A failure ends the run.
    fatal: ClassVar[bool] = False

    def describe(self) -> str:
        return self.label or self.condition.describe()

    def _validate(self, ctx: _Ctx) -> None:
        if not isinstance(self.condition, Condition):
            raise _Bad(f"condition: expected a Condition (Lists(), ...), got {self.condition!r}")
        for name, value in (("within", self.within), ("during", self.during)):
            if value is not None:
                try:
                    Duration.of(value)
                except _Bad as exc:
                    raise _Bad(f"{name}: {exc}") from None
        timed = self.within is not None or self.during is not None
        if self.condition.polled and not timed:
            raise _Bad(f"a {self.condition.kind} check needs within (a deadline) or during")
        if not self.condition.polled and timed:
            raise _Bad(f"a {self.condition.kind} check is judged once: no within or during")
        self.condition._validate(ctx)


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


def _options(options: Mapping[str, Any]) -> None:
    if not isinstance(options, Mapping):
        raise _Bad(f"expected a table of sdfrd options, got {options!r}")
    for key, value in options.items():
        if not isinstance(key, str) or not re.fullmatch(r"[a-z][a-z0-9_]*", key):
            raise _Bad(f"{key!r} is not an sdfrd option name (like miss_limit)")
        if key in RESERVED_OPTIONS:
            what = {"beacon_interval": "beacon", "addressing": "addressing"}.get(key)
            where = f"the scenario's {what}" if what else "the lab"
            raise _Bad(f"{key} is set by {where}")
        if isinstance(value, bool) or not isinstance(value, str | int | float):
            raise _Bad(f"{key}: expected a string or a number, got {value!r}")


def _pairs(robots: Sequence[str], peers: Sequence[str], *, both: bool) -> list[tuple[str, str]]:
    """Ordered pairs (a, b), a != b; with `both`, each unordered pair once."""
    out: list[tuple[str, str]] = []
    seen: set[frozenset[str]] = set()
    for a in robots:
        for b in peers:
            if a == b:
                continue
            if both:
                key = frozenset((a, b))
                if key in seen:
                    continue
                seen.add(key)
            out.append((a, b))
    return out


def _step_ref(index: int, step: Step) -> str:
    return f"step {index} ({step.kind}{f' {step.label!r}' if step.label else ''})"


def _reference(steps: Sequence[Step], index: int, ref: str | None) -> int:
    """The step (1-based) that `ref` (a label or a kind; None: the last action step) names,
    looking back from step `index`."""
    earlier = list(enumerate(steps[: index - 1], 1))
    if ref is None:
        found = [i for i, s in earlier if not isinstance(s, Check)]
        if not found:
            raise _Bad("no action step before it")
        return found[-1]
    labelled = [i for i, s in earlier if s.label == ref]
    if labelled:
        return labelled[-1]
    kinds = [i for i, s in earlier if s.kind == ref]
    if kinds:
        return kinds[-1]
    raise _Bad(f"no earlier step labelled (or of kind) {ref!r}")


def _refers(steps: Sequence[Step], index: int, name: str, ref: str | None) -> int:
    try:
        return _reference(steps, index, ref)
    except _Bad as exc:
        raise _Bad(f"{name}: {exc}") from None


# ---------------------------------------------------------------------------------------------
# The scenario


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
    defends it: ``sdfrd --addressing auto``; what makes a `Collision` collide).
    """

    name: str
    robots: int | Sequence[str] = 3
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
    #: Where it was read from, for messages.
    source: str | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        try:
            self._validate()
        except _Bad as exc:
            raise ScenarioError(f"{self._where()}: {exc}") from None

    def _where(self) -> str:
        name = self.name if isinstance(self.name, str) else "?"
        return self.source or f"scenario {name!r}"

    @property
    def names(self) -> tuple[str, ...]:
        if isinstance(self.robots, int):
            return tuple(f"r{i}" for i in range(1, self.robots + 1))
        return tuple(self.robots)

    def _ctx(self) -> _Ctx:
        return _Ctx(self.names, {g: tuple(m) for g, m in self.groups.items()})

    def _validate(self) -> None:
        if not isinstance(self.name, str) or not re.fullmatch(
            r"[A-Za-z0-9][\w.-]{0,63}", self.name
        ):
            raise _Bad(f"name: 1-64 of letters, digits, '.', '_' and '-', got {self.name!r}")
        if isinstance(self.robots, bool):
            raise _Bad(f"robots: expected a number or a list of names, got {self.robots!r}")
        if isinstance(self.robots, int):
            if not 1 <= self.robots <= naming.MAX_ROBOTS:
                raise _Bad(f"robots: must be 1-{naming.MAX_ROBOTS}, got {self.robots}")
        else:
            if isinstance(self.robots, str) or not self.robots:
                raise _Bad(f"robots: expected a number or a list of names, got {self.robots!r}")
            for r in self.robots:
                try:
                    naming.check_robot_name(r if isinstance(r, str) else repr(r))
                except NetlabError as exc:
                    raise _Bad(f"robots: {exc}") from None
                if r in KEYWORDS:
                    raise _Bad(f"robots: {r!r} is a keyword of selectors, not a robot name")
            if len(set(self.robots)) != len(self.robots):
                raise _Bad(f"robots: names repeat: {list(self.robots)}")
        _number(self.beacon, "beacon", 0.01)
        for name in ("seed", "fleet"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise _Bad(f"{name}: expected a whole number, got {value!r}")
        if not 0 <= self.fleet <= 255:
            raise _Bad(f"fleet: must be 0-255, got {self.fleet}")
        _number(self.radius, "radius", 0.0)
        _size(self.area, "area")
        if self.layout not in LAYOUTS:
            raise _Bad(f"layout: one of {', '.join(LAYOUTS)}, got {self.layout!r}")
        _number(self.spacing, "spacing", 0.0)
        if self.addressing not in ADDRESSING:
            raise _Bad(f"addressing: one of {', '.join(ADDRESSING)}, got {self.addressing!r}")
        if self.capture not in CAPTURE_MODES:
            raise _Bad(f"capture: one of {', '.join(CAPTURE_MODES)}, got {self.capture!r}")
        _number(self.sample, "sample", 0.02, 60.0)
        if not isinstance(self.description, str):
            raise _Bad(f"description: expected text, got {self.description!r}")
        names = self.names
        for robot, pos in self.positions.items():
            if robot not in names:
                raise _Bad(f"positions: unknown robot {robot!r}")
            if not (isinstance(pos, Sequence) and len(pos) == 2):
                raise _Bad(f"positions: {robot}: expected (x, y) in metres, got {pos!r}")
            _number(pos[0], f"positions: {robot}", -1e6, 1e6)
            _number(pos[1], f"positions: {robot}", -1e6, 1e6)
        for group, members in self.groups.items():
            if group in names or group in KEYWORDS:
                raise _Bad(f"groups: {group!r} is a robot name or a keyword; name it otherwise")
            if isinstance(members, str) or not members:
                raise _Bad(f"groups: {group}: expected a list of robot names, got {members!r}")
            for m in members:
                if m not in names:
                    raise _Bad(f"groups: {group}: unknown robot {m!r}")
        _check_field("sdfrd", lambda: _options(self.sdfrd))
        ctx = self._ctx()
        labels: set[str] = set()
        colliding: set[str] = set()
        for i, step in enumerate(self.steps, 1):
            where = _step_ref(i, step) if isinstance(step, Step) else f"step {i}"
            try:
                if not isinstance(step, Step):
                    raise _Bad(f"expected a Step (Start(), Check(...), ...), got {step!r}")
                if step.label is not None:
                    if not isinstance(step.label, str) or not step.label:
                        raise _Bad(f"label: expected a non-empty string, got {step.label!r}")
                    if step.label in labels:
                        raise _Bad(f"label: {step.label!r} is already the label of a step")
                    labels.add(step.label)
                step._validate(ctx)
                cond = step.condition if isinstance(step, Check) else None
                if isinstance(cond, Agreement | Flaps | Resources):
                    _refers(self.steps, i, "over", cond.over)
                if isinstance(cond, Updates):
                    _refers(self.steps, i, "after", cond.after)
                if isinstance(step, Collision):
                    if colliding & set(step.robots):
                        raise _Bad(
                            f"robots: {fmt_set(colliding & set(step.robots))} already in "
                            "another collision; put them in one step"
                        )
                    colliding |= set(step.robots)
            except _Bad as exc:
                raise _Bad(f"{where}: {exc}") from None

    def initial_positions(self) -> dict[str, Pos]:
        names = self.names
        if self.layout == "random":
            rng = random.Random(f"netlab-layout:{self.seed}")
            out = {n: (rng.uniform(0, self.area[0]), rng.uniform(0, self.area[1])) for n in names}
        else:
            out = {n: (i * self.spacing, 0.0) for i, n in enumerate(names)}
        out.update({n: (float(p[0]), float(p[1])) for n, p in self.positions.items()})
        return out

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


# ---------------------------------------------------------------------------------------------
# Scenario files (TOML)


class _Fields:
    """A TOML table's keys taken one by one, with errors naming the field; `done()` rejects the
    rest."""

    def __init__(self, table: Mapping[str, Any], where: str) -> None:
        self.rest = dict(table)
        self.where = where
        self.known: list[str] = []

    def take(self, key: str, conv: Callable[[Any], Any], default: Any = ...) -> Any:
        self.known.append(key)
        if key not in self.rest:
            if default is ...:
                raise ScenarioError(f"{self.where}: {key}: missing")
            return default
        value = self.rest.pop(key)
        try:
            return conv(value)
        except _Bad as exc:
            raise ScenarioError(f"{self.where}: {key}: {exc}") from None

    def done(self) -> None:
        if self.rest:
            extra = ", ".join(sorted(self.rest))
            known = ", ".join(self.known)
            raise ScenarioError(
                f"{self.where}: unknown field{'s' if len(self.rest) > 1 else ''} {extra} "
                f"(this takes: {known})"
            )


def _c_str(v: Any) -> str:
    if not isinstance(v, str):
        raise _Bad(f"expected text, got {v!r}")
    return v


def _c_bool(v: Any) -> bool:
    return _boolean(v)


def _c_int(v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise _Bad(f"expected a whole number, got {v!r}")
    return v


def _c_float(v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise _Bad(f"expected a number, got {v!r}")
    return float(v)


def _c_robots(v: Any) -> Robots:
    if v is True:
        return "all"
    if isinstance(v, str):
        return v
    if isinstance(v, list) and v and all(isinstance(x, str) for x in v):
        return tuple(v)
    raise _Bad(f"expected a robot, a group, 'all' or a list of these, got {v!r}")


def _c_groups(v: Any) -> tuple[Robots, ...]:
    if not isinstance(v, list) or not v:
        raise _Bad(f"expected a list of groups (group names, or lists of robots), got {v!r}")
    return tuple(_c_robots(g) for g in v)


def _c_span(v: Any) -> Duration:
    return Duration.of(v)


def _c_pair(v: Any) -> tuple[float, float]:
    if not (isinstance(v, list) and len(v) == 2):
        raise _Bad(f"expected [x, y], got {v!r}")
    return (_c_float(v[0]), _c_float(v[1]))


def _c_range(v: Any) -> tuple[float, float]:
    """[min, max], or one number for both."""
    if isinstance(v, int | float) and not isinstance(v, bool):
        return (float(v), float(v))
    if not (isinstance(v, list) and len(v) == 2):
        raise _Bad(f"expected [min, max] or a number, got {v!r}")
    return (_c_float(v[0]), _c_float(v[1]))


def _c_table(v: Any) -> dict[str, Any]:
    if not isinstance(v, dict):
        raise _Bad(f"expected a table, got {v!r}")
    return dict(v)


def _c_loss(v: Any) -> float | None:
    if v == "none":
        return None
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise _Bad(f"expected a loss in % or 'none' (back to the range model), got {v!r}")
    return float(v)


def _c_true(v: Any) -> bool:
    if v is not True:
        raise _Bad(f"write `= true`, got {v!r}")
    return True


def _c_names(v: Any) -> tuple[str, ...]:
    if not (isinstance(v, list) and all(isinstance(x, str) for x in v)):
        raise _Bad(f"expected a list of robot names, got {v!r}")
    return tuple(v)


SHAPE_PARAMS = ("delay", "jitter", "loss", "duplicate", "reorder", "corrupt", "rate")


def _parse_condition(kind: str, f: _Fields) -> Condition:
    if kind == "lists":
        return Lists(
            robots=f.take("robots", _c_robots, None),
            groups=f.take("groups", _c_groups, None),
            services=f.take("services", _c_bool, True),
            exact=f.take("exact", _c_bool, True),
        )
    if kind == "medium":
        return Medium(
            robots=f.take("robots", _c_robots, "running"),
            services=f.take("services", _c_bool, False),
        )
    if kind == "unreachable":
        return Unreachable(f.take("robots", _c_robots), on=f.take("on", _c_robots, None))
    if kind == "history":
        return InHistory(
            f.take("robots", _c_robots),
            on=f.take("on", _c_robots, None),
            reachable=f.take("reachable", _c_bool, None),
            indicator_below=f.take("indicator_below", _c_float, None),
            falling=f.take("falling", _c_bool, False),
        )
    if kind == "addresses":
        return DistinctAddresses(robots=f.take("robots", _c_robots, "running"))
    if kind == "agreement":
        return Agreement(
            at_least=f.take("at_least", _c_float, 0.95),
            lag=f.take("lag", _c_span, "1 beacon"),
            loss_lag=f.take("loss_lag", _c_span, None),
            over=f.take("over", _c_str, None),
            measure=f.take("measure", _c_str, "pairs"),
        )
    if kind == "updates":
        return Updates(at_most=f.take("at_most", _c_int, 0), after=f.take("after", _c_str, None))
    if kind == "flaps":
        return Flaps(
            at_most=f.take("at_most", _c_int, 1),
            per=f.take("per", _c_span, "1 min"),
            over=f.take("over", _c_str, None),
        )
    if kind == "indicator":
        return Indicator(
            robots=f.take("robots", _c_robots, "running"),
            tolerance=f.take("tolerance", _c_float, 0.15),
        )
    if kind == "resources":
        return Resources(
            over=f.take("over", _c_str, None),
            cpu_at_most=f.take("cpu_at_most", _c_float, None),
            pss_at_most=f.take("pss_at_most", _c_float, None),
        )
    raise _Bad(f"unknown condition {kind!r} (one of {', '.join(CONDITIONS)})")


def _parse_step(table: Any, where: str) -> Step:
    if not isinstance(table, dict):
        raise ScenarioError(f"{where}: expected a table ([[step]]), got {table!r}")
    actions = [k for k in table if k in STEPS]
    if not actions:
        raise ScenarioError(
            f"{where}: no action; a step has one of: {', '.join(STEPS)} "
            f"(it has: {', '.join(table) or 'nothing'})"
        )
    if len(actions) > 1:
        raise ScenarioError(f"{where}: more than one action ({', '.join(actions)}); one per step")
    kind = actions[0]
    label = table.get("label")
    where = f"{where} ({kind}{f' {label!r}' if isinstance(label, str) else ''})"
    f = _Fields(table, where)
    step: Step
    if kind in ("wait", "check"):
        cond_kind = f.take(kind, _c_str)
        within = f.take("within", _c_span, None)
        during = f.take("during", _c_span, None)
        lab = f.take("label", _c_str, None)
        try:
            cond = _parse_condition(cond_kind, f)
        except _Bad as exc:
            raise ScenarioError(f"{where}: {kind}: {exc}") from None
        cls = Wait if kind == "wait" else Check
        step = cls(cond, within=within, during=during, label=lab)
    else:
        step = _parse_action(kind, f)
    f.done()
    return step


def _parse_action(kind: str, f: _Fields) -> Step:
    label = f.take("label", _c_str, None)
    if kind == "start":
        return Start(f.take(kind, _c_robots), f.take("options", _c_table, {}), label=label)
    if kind == "stop":
        return Stop(f.take(kind, _c_robots), label=label)
    if kind == "kill":
        return Kill(f.take(kind, _c_robots), label=label)
    if kind == "restart":
        return Restart(f.take(kind, _c_robots), hard=f.take("hard", _c_bool, False), label=label)
    if kind == "partition":
        return Partition(f.take(kind, _c_groups), label=label)
    if kind == "merge":
        f.take(kind, _c_true)
        return Merge(label=label)
    if kind == "move":
        return Move(f.take(kind, _c_str), f.take("to", _c_pair), label=label)
    if kind == "mobility":
        return Mobility(
            f.take(kind, _c_robots),
            duration=f.take("duration", _c_span),
            quick=f.take("quick", _c_span, None),
            speed=f.take("speed", _c_range, (0.5, 1.5)),
            pause=f.take("pause", _c_range, (0.0, 2.0)),
            area=f.take("area", _c_pair, None),
            seed=f.take("seed", _c_int, None),
            tick=f.take("tick", _c_float, 0.5),
            label=label,
        )
    if kind == "quality":
        return Quality(
            f.take(kind, _c_robots),
            peers=f.take("peers", _c_robots, None),
            loss=f.take("loss", _c_loss),
            both=f.take("both", _c_bool, True),
            label=label,
        )
    if kind == "shape":
        robots = f.take(kind, _c_robots)
        params = {p: f.take(p, lambda v: v) for p in SHAPE_PARAMS if p in f.rest}
        f.known.extend(SHAPE_PARAMS)
        return Shape(robots, params, label=label)
    if kind == "publish":
        return Publish(
            f.take(kind, _c_robots),
            f.take("service", _c_str),
            f.take("type", _c_str),
            url=f.take("url", _c_str, None),
            attributes=f.take("attributes", _c_table, {}),
            label=label,
        )
    if kind == "unpublish":
        return Unpublish(f.take(kind, _c_robots), f.take("service", _c_str), label=label)
    if kind == "collision":
        return Collision(f.take(kind, _c_names), label=label)
    if kind == "sleep":
        return Sleep(f.take(kind, _c_span), quick=f.take("quick", _c_span, None), label=label)
    raise AssertionError(kind)  # STEPS and this function list the same kinds


TOP_LEVEL = ("scenario", "groups", "positions", "sdfrd", "step")


def from_dict(
    data: Mapping[str, Any], source: str = "<scenario>", name: str | None = None
) -> Scenario:
    """A Scenario from a parsed scenario file (see the module's documentation)."""
    extra = [k for k in data if k not in TOP_LEVEL]
    if extra:
        raise ScenarioError(
            f"{source}: unknown table or key {', '.join(map(repr, extra))} (a scenario file has "
            "[scenario], [groups], [positions], [sdfrd] and [[step]])"
        )
    head = data.get("scenario", {})
    if not isinstance(head, dict):
        raise ScenarioError(f"{source}: [scenario] must be a table")
    f = _Fields(head, f"{source}: [scenario]")

    def robots(v: Any) -> int | tuple[str, ...]:
        if isinstance(v, int) and not isinstance(v, bool):
            return v
        return _c_names(v)

    kw: dict[str, Any] = {
        "name": f.take("name", _c_str, name),
        "description": f.take("description", _c_str, ""),
        "robots": f.take("robots", robots, 3),
        "beacon": f.take("beacon", _c_float, 1.0),
        "seed": f.take("seed", _c_int, 0),
        "fleet": f.take("fleet", _c_int, 1),
        "radius": f.take("radius", _c_float, 50.0),
        "area": f.take("area", _c_pair, HALL),
        "layout": f.take("layout", _c_str, "line"),
        "spacing": f.take("spacing", _c_float, 1.0),
        "capture": f.take("capture", _c_str, "all"),
        "sample": f.take("sample", _c_float, 0.25),
        "addressing": f.take("addressing", _c_str, "manual"),
    }
    f.done()
    if kw["name"] is None:
        raise ScenarioError(f"{source}: [scenario]: name: missing")
    tables: dict[str, dict[str, Any]] = {}
    for key in ("groups", "positions", "sdfrd"):
        value = data.get(key, {})
        if not isinstance(value, dict):
            raise ScenarioError(f"{source}: [{key}] must be a table")
        tables[key] = value
    groups = {}
    for g, members in tables["groups"].items():
        try:
            groups[g] = _c_names(members)
        except _Bad as exc:
            raise ScenarioError(f"{source}: [groups]: {g}: {exc}") from None
    positions = {}
    for r, pos in tables["positions"].items():
        try:
            positions[r] = _c_pair(pos)
        except _Bad as exc:
            raise ScenarioError(f"{source}: [positions]: {r}: {exc}") from None
    raw_steps = data.get("step", [])
    if not isinstance(raw_steps, list):
        raise ScenarioError(f"{source}: steps are written as [[step]] tables")
    steps = [_parse_step(t, f"{source}: step {i}") for i, t in enumerate(raw_steps, 1)]
    return Scenario(
        steps=steps,
        groups=groups,
        positions=positions,
        sdfrd=tables["sdfrd"],
        source=source,
        **kw,
    )


def loads(text: str, source: str = "<scenario>", name: str | None = None) -> Scenario:
    """A Scenario from TOML text; ScenarioError names the line, step or field that is wrong."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{source}: not valid TOML: {exc}") from None
    return from_dict(data, source, name)


def load(path: Path | str) -> Scenario:
    """A Scenario from a TOML file (its name defaults to the file's stem)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ScenarioError(f"cannot read scenario file {path}: {exc.strerror or exc}") from None
    return loads(text, str(path), name=path.stem)


def bundled() -> dict[str, Path]:
    """The bundled scenario files, by name."""
    return {p.stem: p for p in sorted(BUNDLED_DIR.glob("*.toml"))}


def find(ref: str) -> Path:
    """A scenario file: `ref` itself if it is a file, else the bundled scenario of that name."""
    path = Path(ref)
    if path.is_file():
        return path
    found = bundled().get(ref)
    if found is not None:
        return found
    raise ScenarioError(
        f"no scenario file {ref!r} and no bundled scenario of that name "
        f"(bundled: {', '.join(bundled())})"
    )


# ---------------------------------------------------------------------------------------------
# What the engine needs of a lab (netlab.lab.Lab; tests may give a fake)


class RobotLike(Protocol):
    @property
    def ns(self) -> str: ...

    @property
    def mac(self) -> str: ...

    @property
    def log(self) -> Path: ...


class MediumLike(Protocol):
    @property
    def ns(self) -> str: ...


class LabLike(Protocol):
    @property
    def name(self) -> str: ...

    @property
    def medium(self) -> MediumLike: ...

    def up(self) -> object: ...

    def down(self) -> object: ...

    def add_robot(self, name: str, *, pos: Pos = ..., mac: str | None = ...) -> object: ...

    def robot(self, ref: str) -> RobotLike: ...

    def batch(self) -> AbstractContextManager[None]: ...

    def start_all(
        self, refs: Iterable[str] | None = ..., *, timeout: float = ..., **options: Any
    ) -> None: ...

    def start(self, ref: str, *, timeout: float = ..., **options: Any) -> None: ...

    def stop(self, ref: str, timeout: float = ...) -> int: ...

    def kill(self, ref: str) -> None: ...

    def restart(self, ref: str, *, timeout: float = ..., **options: Any) -> None: ...

    def partition(self, groups: Iterable[Iterable[str]]) -> None: ...

    def merge(self) -> None: ...

    def move(self, ref: str, pos: Pos) -> None: ...

    def set_pair_quality(self, a: str, b: str, *, loss: float | None, both: bool = ...) -> None: ...

    def shape(self, ref: str, **params: Any) -> object: ...

    def links(self) -> Mapping[tuple[str, str], float]: ...

    def positions(self) -> dict[str, Pos]: ...


@dataclass(frozen=True, slots=True)
class LabSpec:
    """The lab a scenario asks for."""

    name: str
    seed: int
    fleet: int
    range_model: RangeModel
    addressing: str = "manual"


def _real_lab(spec: LabSpec) -> LabLike:
    import inspect

    from netlab.lab import Lab

    extra: dict[str, Any] = {}
    if spec.addressing != "manual":
        if "addressing" not in inspect.signature(Lab).parameters:
            raise NetlabError(f"this netlab's Lab cannot do addressing = {spec.addressing}")
        extra["addressing"] = spec.addressing
    return Lab(spec.name, seed=spec.seed, fleet=spec.fleet, range_model=spec.range_model, **extra)


def _real_client(lab: LabLike, robot: str) -> ClientLike:
    from netlab.lab import Lab
    from sdfr.client import Client

    assert isinstance(lab, Lab)
    return Client(unix_socket=lab.robot(robot).api_socket, timeout=2.0)


@cache
def sdfrd_flags() -> frozenset[str]:
    """The options `sdfrd --help` lists (as the lab runs it), without dashes."""
    try:
        res = subprocess.run(
            [sys.executable, "-m", "sdfr.daemon.supervisor", "--help"],
            capture_output=True,
            text=True,
            timeout=60,
            stdin=subprocess.DEVNULL,
        )
    except (OSError, subprocess.SubprocessError) as exc:
        raise NetlabError(f"cannot run sdfrd --help: {exc}") from None
    return frozenset(m.replace("-", "_") for m in re.findall(r"--([a-z][a-z0-9-]*)", res.stdout))


@dataclass(frozen=True)
class Backend:
    """How the engine makes a lab, talks to a robot's daemon, and learns sdfrd's options."""

    make_lab: Callable[[LabSpec], LabLike] = _real_lab
    connect: Callable[[LabLike, str], ClientLike] = _real_client
    flags: Callable[[], frozenset[str]] = sdfrd_flags
    #: Whether tcpdump can run in the lab's namespaces.
    can_capture: bool = True


# ---------------------------------------------------------------------------------------------
# Results


@dataclass
class CheckResult:
    """How one check went: ok True/False, or None when it could not be judged (skipped)."""

    step: int
    kind: str
    description: str
    fatal: bool
    ok: bool | None = None
    took: float | None = None  # seconds from the event to the condition holding
    deadline: float | None = None  # seconds
    during: float | None = None
    at: float = 0.0  # seconds since the run's timeline began
    detail: str = ""
    data: dict[str, Any] = field(default_factory=dict)

    @property
    def result(self) -> str:
        return {True: "ok", False: "FAILED", None: "skipped"}[self.ok]

    def to_json(self) -> dict[str, Any]:
        return {
            "step": self.step,
            "kind": self.kind,
            "description": self.description,
            "fatal": self.fatal,
            "ok": self.ok,
            "result": self.result,
            "took_s": self.took,
            "deadline_s": self.deadline,
            "during_s": self.during,
            "at_s": self.at,
            "detail": self.detail,
            **({"data": self.data} if self.data else {}),
        }


@dataclass
class RunResult:
    """How a scenario run went: status "passed", "failed", "error" or "skipped"."""

    scenario: str
    status: str
    run_dir: Path | None = None
    checks: list[CheckResult] = field(default_factory=list)
    error: str | None = None
    reason: str | None = None  # why it was skipped
    robots: int = 0
    beacon: float = 0.0
    duration: float = 0.0
    report: dict[str, Any] | None = None

    @property
    def ok(self) -> bool:
        return self.status == "passed"

    @property
    def failed(self) -> list[CheckResult]:
        return [c for c in self.checks if c.ok is False]

    def to_json(self) -> dict[str, Any]:
        return {
            "scenario": self.scenario,
            "status": self.status,
            "run_dir": str(self.run_dir) if self.run_dir else None,
            "error": self.error,
            "reason": self.reason,
            "robots": self.robots,
            "beacon_interval_s": self.beacon,
            "duration_s": self.duration,
            "checks": [c.to_json() for c in self.checks],
        }

    def summary(self) -> list[str]:
        """The checks as a table, and a closing line."""
        lines = [f"{'step':>4}  {'check':54} {'deadline':>9} {'took':>8}  result"]
        for c in self.checks:
            deadline = f"{c.deadline:.2f} s" if c.deadline is not None else "-"
            if c.during is not None:
                deadline = f"for {c.during:.2f} s" if c.deadline is None else f"{deadline}+"
            took = f"{c.took:.2f} s" if c.took is not None else "-"
            desc = c.description if len(c.description) <= 54 else c.description[:51] + "..."
            lines.append(f"{c.step:>4}  {desc:54} {deadline:>9} {took:>8}  {c.result}")
            if c.ok is not True and c.detail:
                lines.append(f"{'':6}{c.detail}")
        ok = sum(c.ok is True for c in self.checks)
        tail = f"{self.scenario}: {self.status.upper()}, {ok} of {len(self.checks)} checks ok"
        lines.append(f"{tail}, in {self.duration:.1f} s")
        if self.error:
            lines.append(f"error: {self.error}")
        return lines


# ---------------------------------------------------------------------------------------------
# Running


_lab_counter = itertools.count()


def default_lab_name() -> str:
    """'s' + this process (4 base-36 digits) + a counter: unique on this machine for a while."""
    return f"s{naming.b36(os.getpid() % 36**4, 4)}{naming.b36(next(_lab_counter) % 36**3)}"


def _new_run_dir(runs: Path, name: str) -> Path:
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    base = Path(runs).absolute() / f"{name}-{stamp}"
    for n in itertools.count(1):
        path = base if n == 1 else base.with_name(f"{base.name}-{n}")
        try:
            path.mkdir(parents=True)
            return path
        except FileExistsError:
            continue
    raise AssertionError("unreachable")


def missing_requirements(scenario: Scenario, flags: frozenset[str]) -> str | None:
    """Why this sdfrd cannot run the scenario (an option it lacks), or None."""
    missing = sorted(o for o in scenario.sdfrd_options() if o not in flags)
    if not missing:
        return None
    opts = ", ".join("--" + o.replace("_", "-") for o in missing)
    reason = f"sdfrd has no {opts} option (not in `sdfrd --help`)"
    if "addressing" in missing:
        reason += (
            "; addressing = auto (what makes a collision step collide) needs sdfrd's address "
            "self-configuration, which this sdfrd does not have yet"
        )
    return reason


def _say(line: str) -> None:
    print(line, flush=True)


def run(
    scenario: Scenario,
    *,
    lab_name: str | None = None,
    run_dir: Path | None = None,
    runs: Path = Path("runs"),
    quick: bool = False,
    capture: str | None = None,
    report: bool = True,
    say: Callable[[str], None] = _say,
    backend: Backend | None = None,
) -> RunResult:
    """Run `scenario` on a new lab (always taken down); progress goes to `say`.

    The run folder is `run_dir`, or a new ``runs/<name>-<time>``.  `quick` uses the steps'
    `quick` durations; `capture` overrides the scenario's.  Skipped (status "skipped", with
    the reason said) when sdfrd lacks an option the scenario needs.
    """
    backend = backend or Backend()
    if capture is not None:
        scenario = replace(scenario, capture=capture)
    if not backend.can_capture:
        scenario = replace(scenario, capture="none")
    head = (
        f"scenario {scenario.name}: {len(scenario.names)} robots, beacon {scenario.beacon:g} s"
        f"{' (the product default is 10 s)' if scenario.beacon != PRODUCT_BEACON else ''}"
    )
    reason = missing_requirements(scenario, backend.flags())
    if reason is not None:
        say(f"{head}\n  SKIPPED: {reason}")
        return RunResult(
            scenario.name,
            "skipped",
            reason=reason,
            robots=len(scenario.names),
            beacon=scenario.beacon,
        )
    folder = Path(run_dir).absolute() if run_dir is not None else _new_run_dir(runs, scenario.name)
    folder.mkdir(parents=True, exist_ok=True)
    say(f"{head}{', quick' if quick else ''}; run folder {folder}")
    engine = _Run(scenario, backend, folder, lab_name or default_lab_name(), quick, say)
    return engine.execute(report=report)


class _Run:
    """One run of a scenario: the lab, the captures, the observer, the timeline, the report."""

    def __init__(
        self,
        sc: Scenario,
        backend: Backend,
        run_dir: Path,
        lab_name: str,
        quick: bool,
        say: Callable[[str], None],
    ) -> None:
        self.sc = sc
        self.ctx = sc._ctx()
        self.backend = backend
        self.run_dir = run_dir
        self.quick = quick
        self._say = say
        spec = LabSpec(lab_name, sc.seed, sc.fleet, UnitDisc(sc.radius), sc.addressing)
        self.lab = backend.make_lab(spec)
        self.truth = TruthLog()
        self.running: list[str] = []
        self.services: dict[str, dict[str, str]] = {n: {} for n in sc.names}
        self.windows: dict[int, tuple[float, float]] = {}
        self.checks: list[CheckResult] = []
        self.pending: list[tuple[CheckResult, Updates, float, float]] = []
        self.error: str | None = None
        self.t0 = time.monotonic()
        self.event = self.t0  # end of the last action step
        self.probe: Probe | None = None
        self.observer: Observer | None = None
        self.samples: list[Sample] = []
        self.captured = False
        self.wall = (time.time(), time.time())
        self.action_wall = time.time()  # start of the last action step (wall clock)
        self._baseline: tuple[float, dict[str, dict[str, float]]] | None = None
        #: Steps whose window a resources check measures -> readings at its start and end.
        self.measured = {
            _reference(sc.steps, i, s.condition.over)
            for i, s in enumerate(sc.steps, 1)
            if isinstance(s, Check) and isinstance(s.condition, Resources)
        }
        self.usage: dict[int, tuple[dict[str, Any], dict[str, Any]]] = {}

    # -- output ------------------------------------------------------------------------------

    def say(self, text: str) -> None:
        self._say(f"  {time.monotonic() - self.t0:7.2f} s  {text}")

    # -- the run -----------------------------------------------------------------------------

    def execute(self, *, report: bool) -> RunResult:
        start_wall = time.time()
        self.t0 = time.monotonic()
        captures: list[Any] = []
        try:
            self.lab.up()
        except NetlabError as exc:
            self.say(f"ERROR {exc}")
            return RunResult(self.sc.name, "error", self.run_dir, error=str(exc))
        try:
            try:
                self._add_robots()
                captures = self._start_captures()
                self.probe = Probe(lambda r: self.backend.connect(self.lab, r))
                self.observer = Observer(
                    Probe(lambda r: self.backend.connect(self.lab, r)), self.truth, self.sc.sample
                ).start()
                self._timeline()
            finally:
                self._teardown(captures)
        except (NetlabError, ApiError) as exc:
            self.error = self.error or str(exc)
            self.say(f"ERROR {exc}")
        self.wall = (start_wall, time.time())
        status = (
            "error"
            if self.error
            else "failed"
            if any(c.ok is False for c in self.checks)
            else "passed"
        )
        result = RunResult(
            self.sc.name,
            status,
            self.run_dir,
            self.checks,
            error=self.error,
            robots=len(self.sc.names),
            beacon=self.sc.beacon,
            duration=time.monotonic() - self.t0,
        )
        self._finish(result, report)
        return result

    def _add_robots(self) -> None:
        t = time.monotonic()
        positions = self.sc.initial_positions()
        together = {r: group for group in self.sc.collisions() for r in group}
        added: set[str] = set()
        with self.lab.batch():
            for name in self.sc.names:
                # The first of a collision gets its own MAC; each other one a twin of it.
                group = together.get(name, ())
                first = next((r for r in group if r in added), None)
                mac = None
                if first is not None:
                    mac = twin_mac(self.lab.robot(first).mac, group.index(name))
                self.lab.add_robot(name, pos=positions[name], mac=mac)
                added.add(name)
        self._record_truth()
        n = len(self.sc.names)
        self.say(
            f"lab {self.lab.name} up: {n} robots on one medium in {time.monotonic() - t:.2f} s"
        )

    def _start_captures(self) -> list[Any]:
        mode = self.sc.capture
        if mode == "none":
            return []
        from netlab.capture import Capture, start_all

        caps: list[Capture] = []
        if mode in ("all", "medium"):
            caps.append(
                Capture(
                    self.lab.medium.ns, naming.BRIDGE, self.run_dir / "medium.pcap", label="medium"
                )
            )
        if mode in ("all", "robots"):
            caps += [
                Capture(
                    self.lab.robot(n).ns,
                    naming.ROBOT_IFACE,
                    self.run_dir / f"{n}.pcap",
                    label=n,
                )
                for n in self.sc.names
            ]
        t = time.monotonic()
        start_all(caps)
        self.captured = True
        what = {"all": "the medium and every robot", "robots": "every robot"}.get(mode, mode)
        self.say(f"capturing on {what} ({len(caps)} tcpdumps, {time.monotonic() - t:.2f} s)")
        return caps

    def _teardown(self, captures: list[Any]) -> None:
        if self.observer is not None:
            self.samples = self.observer.stop()
        if self.probe is not None:
            self.probe.close()
        try:
            if captures:
                from netlab.capture import CaptureError, stop_all

                try:
                    stop_all(captures)
                except CaptureError as exc:
                    self.say(f"warning: {exc}")
        finally:
            self._keep_logs()
            self.lab.down()

    def _keep_logs(self) -> None:
        logs = self.run_dir / "logs"
        for name in self.sc.names:
            with contextlib.suppress(NetlabError, OSError):
                src = self.lab.robot(name).log
                if src.exists():
                    logs.mkdir(exist_ok=True)
                    shutil.copyfile(src, logs / f"{name}.log")

    def _timeline(self) -> None:
        for i, step in enumerate(self.sc.steps, 1):
            wall = time.time()
            try:
                if isinstance(step, Check):
                    ok = self._check(i, step)
                else:
                    self.action_wall = wall
                    before = self._usage() if i in self.measured else None
                    self.say(self._act(step))
                    self.event = time.monotonic()
                    if before is not None:
                        self.usage[i] = (before, self._usage())
                    ok = True
            except (NetlabError, ApiError, _Bad) as exc:
                self.error = f"{_step_ref(i, step)}: {exc}"
                self.say(f"ERROR {self.error}")
                return
            finally:
                self.windows[i] = (wall, time.time())
            if not ok and isinstance(step, Check) and step.fatal:
                self.say(f"stopping: {_step_ref(i, step)} failed and later steps rely on it")
                return

    def _record_truth(self) -> TruthState:
        # A robot's own link loss can add up to 100 %: no datagram passes, so no link.
        links = [pair for pair, loss in self.lab.links().items() if loss < 100.0]
        return self.truth.record(links, self.running)

    def _usage(self) -> dict[str, Any]:
        """A /proc reading of each running daemon's process tree (empty when the lab cannot
        tell its daemons' pids)."""
        pid_of = getattr(self.lab, "daemon_pid", None)
        if pid_of is None:
            return {}
        kids = procstat.children()
        out: dict[str, Any] = {}
        for name in self.running:
            pid = pid_of(name)
            if pid is not None:
                out[name] = procstat.Usage.read(procstat.tree(pid, kids))
        return out

    def _names(self, sel: Robots) -> tuple[str, ...]:
        return self.ctx.robots(sel, self.running)

    def _options(self, step: Start | None = None) -> dict[str, Any]:
        return {
            "beacon_interval": self.sc.beacon,
            **self.sc.sdfrd,
            **(step.options if step is not None else {}),
        }

    def _text(self, names: Sequence[str]) -> str:
        if len(names) > 2 and set(names) == set(self.sc.names):
            return f"all {len(names)}"
        return ", ".join(names)

    # -- actions -----------------------------------------------------------------------------

    def _act(self, step: Step) -> str:
        lab = self.lab
        if isinstance(step, Start):
            names = self._names(step.robots)
            t = time.monotonic()
            lab.start_all(names, timeout=max(60.0, 2.0 * len(names)), **self._options(step))
            self.running += [n for n in names if n not in self.running]
            self._record_truth()
            took = time.monotonic() - t
            return f"start {self._text(names)}: sdfrd healthy on {len(names)} in {took:.2f} s"
        if isinstance(step, Stop):
            names = self._names(step.robots)
            for n in names:
                lab.stop(n)
                self._gone(n)
            return f"stop {self._text(names)} (SIGTERM: Byebye)"
        if isinstance(step, Kill):
            names = self._names(step.robots)
            for n in names:
                lab.kill(n)
                self._gone(n)
            return f"kill -9 {self._text(names)} (silent)"
        if isinstance(step, Restart):
            names = self._names(step.robots)
            for n in names:
                if step.hard:
                    if n in self.running:
                        lab.kill(n)
                        self._gone(n)
                    lab.start(n, **self._options())
                else:
                    lab.restart(n, **self._options())
                if n not in self.running:
                    self.running.append(n)
                self._record_truth()
            return f"restart {self._text(names)} ({'kill -9' if step.hard else 'SIGTERM'}, start)"
        if isinstance(step, Partition):
            groups = _groups(self.ctx, step.groups)
            lab.partition(groups)
            self._record_truth()
            rest = [n for n in self.sc.names if not any(n in g for g in groups)]
            text = " | ".join(fmt_set(g) for g in [*groups, *([rest] if rest else [])])
            return f"partition {text}"
        if isinstance(step, Merge):
            lab.merge()
            self._record_truth()
            return "merge: the partition ends"
        if isinstance(step, Move):
            lab.move(step.robot, (float(step.to[0]), float(step.to[1])))
            hears = {a for (a, b) in self._record_truth().links if b == step.robot}
            where = f"({step.to[0]:g}, {step.to[1]:g})"
            return f"move {step.robot} to {where}: in range of {fmt_set(hears)}"
        if isinstance(step, Mobility):
            return self._mobility(step)
        if isinstance(step, Quality):
            names = self._names(step.robots)
            peers = self._names(step.peers) if step.peers is not None else names
            pairs = _pairs(names, peers, both=step.both)
            with lab.batch():
                for a, b in pairs:
                    lab.set_pair_quality(a, b, loss=step.loss, both=step.both)
            self._record_truth()
            what = "back to the range model" if step.loss is None else f"{step.loss:g} % loss"
            ways = "both ways" if step.both else "one way"
            return f"quality: {what} on {len(pairs)} pair{'s' if len(pairs) > 1 else ''} ({ways})"
        if isinstance(step, Shape):
            names = self._names(step.robots)
            for n in names:
                lab.shape(n, **dict(step.params))
            self._record_truth()
            params = ", ".join(f"{k} {v}" for k, v in step.params.items()) or "no shaping"
            return f"shape {self._text(names)}: {params}"
        if isinstance(step, Publish):
            names = self._names(step.robots)
            for n in names:
                self._need_running(n, "publish")
                if step.service in self.services[n]:
                    raise StepError(f"{n} already has a service {step.service!r} from this run")
                assert self.probe is not None
                sid = self.probe.client(n).publish(
                    step.service, step.type, step.url, dict(step.attributes)
                )
                self.services[n][step.service] = sid
            return f"publish {step.service!r} ({step.type}) on {self._text(names)}"
        if isinstance(step, Unpublish):
            names = self._names(step.robots)
            for n in names:
                self._need_running(n, "unpublish")
                known = self.services[n].get(step.service)
                if known is None:
                    raise StepError(f"{n} has no service {step.service!r} published by this run")
                assert self.probe is not None
                self.probe.client(n).unpublish(known)
                del self.services[n][step.service]
            return f"unpublish {step.service!r} on {self._text(names)}"
        if isinstance(step, Collision):
            macs = ", ".join(f"{r} {self.lab.robot(r).mac}" for r in step.robots)
            auto = self.sc.addressing == "auto"
            note = "" if auto else "; it matters only with addressing = auto, not set here"
            return (
                f"collision: MACs ending alike, one derived address: {macs} (at lab creation{note})"
            )
        if isinstance(step, Sleep):
            span = step.quick if self.quick and step.quick is not None else step.duration
            wait = seconds(span, self.sc.beacon)
            time.sleep(wait)
            return f"slept {wait:g} s"
        raise AssertionError(f"no action for {step!r}")

    def _gone(self, name: str) -> None:
        if name in self.running:
            self.running.remove(name)
        self._record_truth()

    def _need_running(self, name: str, what: str) -> None:
        if name not in self.running:
            raise StepError(f"cannot {what} on {name}: its sdfrd is not running")

    def _mobility(self, step: Mobility) -> str:
        names = self._names(step.robots)
        span = step.quick if self.quick and step.quick is not None else step.duration
        duration = seconds(span, self.sc.beacon)
        area = step.area or self.sc.area
        here = self.lab.positions()
        model = RandomWaypoint(
            names,
            area=area,
            speed=step.speed,
            pause=step.pause,
            seed=self.sc.seed if step.seed is None else step.seed,
            start={n: here[n] for n in names},
        )
        self.say(
            f"mobility: random waypoint for {len(names)} robots in {area[0]:g} x {area[1]:g} m "
            f"at {step.speed[0]:g}-{step.speed[1]:g} m/s, {duration:g} s"
        )
        t0 = time.monotonic()
        changes = 0
        linked: list[int] = []
        last = self.truth.now()
        report_every = max(10.0, duration / 6)
        next_report = report_every
        k = 0
        while k * step.tick <= duration + 1e-9:
            with self.lab.batch():
                for name, pos in model.positions_at(k * step.tick).items():
                    self.lab.move(name, pos)
            state = self._record_truth()
            changes += len({frozenset(p) for p in state.links ^ last.links})
            linked.append(state.linked_pairs())
            last = state
            k += 1
            if k * step.tick >= next_report and k * step.tick <= duration:
                self.say(
                    f"mobility: {k * step.tick:.0f} of {duration:g} s, {linked[-1]} pairs "
                    f"linked, {changes} link changes so far"
                )
                next_report += report_every
            wait = t0 + k * step.tick - time.monotonic()
            if wait > 0 and k * step.tick <= duration + 1e-9:
                time.sleep(wait)
        pairs = len(names) * (len(names) - 1) // 2
        mean = sum(linked) / len(linked) if linked else 0.0
        return (
            f"mobility done: {changes} link changes in {duration:g} s, "
            f"{mean:.1f} of {pairs} pairs linked on average"
        )

    # -- checks ------------------------------------------------------------------------------

    def _check(self, index: int, step: Check) -> bool:
        cond = step.condition
        res = CheckResult(index, cond.kind, step.describe(), step.fatal)
        self.checks.append(res)
        if isinstance(cond, Agreement):
            self._agreement(index, step, cond, res)
        elif isinstance(cond, Flaps):
            self._flaps(index, cond, res)
        elif isinstance(cond, Resources):
            self._resources(index, cond, res)
        elif isinstance(cond, Updates):
            ref = _reference(self.sc.steps, index, cond.after)
            if not self.captured:
                res.detail = "needs captures (capture is 'none'): not judged"
                self.say(f"skip  {res.description}: {res.detail}")
                res.at = time.monotonic() - self.t0
                return True
            self.pending.append((res, cond, self.windows[ref][0], time.time()))
            res.at = time.monotonic() - self.t0
            self.say(f"...   {res.description}: counted in the captures at the end")
            return True
        else:
            self._poll(step, res)
            if isinstance(cond, Indicator):
                self._indicator_data(cond, res)
        return res.ok is not False

    def _poll(self, step: Check, res: CheckResult) -> None:
        beacon = self.sc.beacon
        within = seconds(step.within, beacon) if step.within is not None else 0.0
        during = seconds(step.during, beacon) if step.during is not None else None
        res.deadline = within if step.within is not None else None
        res.during = during
        since = self.event
        period = min(0.1, max(0.02, within / 20))
        first = True
        late: list[str] = []  # what was wrong at the deadline
        while True:
            problems = self._evaluate(step.condition)
            now = time.monotonic()
            if not problems and (first or now - since <= within):
                # At a first look after the deadline (earlier checks took that long) it
                # holds, but since when is not known: say so.
                res.took = now - since
                if now - since > within:
                    res.detail = f"first looked at {now - since:.2f} s, after the deadline"
                break
            if now - since > within and not first:
                res.ok = False
                res.at = now - self.t0
                if problems:
                    res.detail = "; ".join(problems)
                else:
                    res.detail = f"held from {now - since:.2f} s; at the deadline: " + "; ".join(
                        late
                    )
                self.say(f"FAIL  {res.description}: not within {within:.2f} s: {res.detail}")
                return
            if now - since <= within:
                late = problems
            first = False
            time.sleep(period)
        if during:
            held_from = time.monotonic()
            end = held_from + during
            while time.monotonic() < end:
                time.sleep(min(period, max(0.0, end - time.monotonic())))
                problems = self._evaluate(step.condition)
                if problems:
                    res.ok = False
                    res.at = time.monotonic() - self.t0
                    held = time.monotonic() - held_from
                    res.detail = f"held {held:.2f} of {during:g} s, then: " + "; ".join(problems)
                    self.say(f"FAIL  {res.description}: {res.detail}")
                    return
        res.ok = True
        res.at = time.monotonic() - self.t0
        if step.within is None:
            res.took = None  # it had to hold from the first look: there is no "when"
            self.say(f"ok    {res.description}: held {during or 0:g} s")
        else:
            kept = f", then held {during:g} s" if during else ""
            note = f" ({res.detail})" if res.detail else ""
            self.say(
                f"ok    {res.description}: {res.took or 0.0:.2f} s (deadline {within:.2f} s)"
                f"{kept}{note}"
            )

    def _evaluate(self, cond: Condition) -> list[str]:
        assert self.probe is not None
        probe = self.probe
        running = set(self.running)
        if isinstance(cond, Lists):
            if cond.groups is not None:
                groups = _groups(self.ctx, cond.groups)
            else:
                groups = [self._names(cond.robots if cond.robots is not None else "running")]
            expected: dict[str, set[str]] = {}
            for g in groups:
                members = [r for r in g if r in running]
                if not members:
                    return [f"no robot of {fmt_set(g)} runs"]
                expected.update({a: set(members) - {a} for a in members})
            views = probe.neighbours(expected)
            services = {r: set(s) for r, s in self.services.items()} if cond.services else None
            return expect_problems(views, expected, services=services, exact=cond.exact)
        if isinstance(cond, Medium):
            state = self.truth.now()
            robots = [r for r in self._names(cond.robots) if r in running]
            expected = {a: state.expected(a) for a in robots}
            services = {r: set(s) for r, s in self.services.items()} if cond.services else None
            return expect_problems(probe.neighbours(robots), expected, services=services)
        if isinstance(cond, Unreachable):
            gone = self._names(cond.robots)
            on = self._names(cond.on) if cond.on is not None else self.running
            on = [r for r in on if r in running and r not in gone]
            return unreachable_problems(probe.neighbours(on), gone, on)
        if isinstance(cond, InHistory):
            kept = self._names(cond.robots)
            on = self._names(cond.on) if cond.on is not None else self.running
            on = [r for r in on if r in running and r not in kept]
            fell_from = self._indicators_before_last_step() if cond.falling else None
            return history_problems(
                probe.histories(on),
                kept,
                on,
                reachable=cond.reachable,
                indicator_below=cond.indicator_below,
                fell_from=fell_from,
            )
        if isinstance(cond, Indicator):
            robots = [r for r in self._names(cond.robots) if r in running]
            return indicator_problems(probe.neighbours(robots), self._rates(), cond.tolerance)
        if isinstance(cond, DistinctAddresses):
            robots = [r for r in self._names(cond.robots) if r in running]
            return address_problems(probe.neighbours(robots), probe.addresses(robots))
        raise AssertionError(f"{cond.kind} is not polled")

    def _indicators_before_last_step(self) -> dict[str, dict[str, float]]:
        """Each robot's indicators in the last samples before the last action step began,
        worked out once per step (a polled check asks again and again)."""
        if self._baseline is None or self._baseline[0] != self.action_wall:
            assert self.observer is not None
            seen = indicators_before(self.observer.samples, self.action_wall)
            self._baseline = (self.action_wall, seen)
        return self._baseline[1]

    def _rates(self) -> dict[tuple[str, str], float]:
        """(robot, peer) -> the share of robot's pings to peer the medium lets come back."""
        links = self.lab.links()  # (sender, receiver) -> loss in %
        return {
            (a, b): (1 - loss / 100.0) * (1 - links[(b, a)] / 100.0)
            for (a, b), loss in links.items()
            if (b, a) in links
        }

    def _indicator_data(self, cond: Indicator, res: CheckResult) -> None:
        assert self.probe is not None
        robots = [r for r in self._names(cond.robots) if r in self.running]
        rates = self._rates()
        seen: dict[str, dict[str, float | None]] = {}
        errors: list[float] = []
        for robot, view in self.probe.neighbours(robots).items():
            seen[robot] = {}
            for peer in natural_order(list(view.reachable)):
                entry = view.entry(peer)
                ind = entry.indicator if entry is not None else None
                seen[robot][peer] = ind
                if ind is not None and (robot, peer) in rates:
                    errors.append(abs(ind - rates[(robot, peer)]))
        values = sorted(rates.values())
        res.data = {
            "indicators": seen,
            "medium_round_trip": {"min": values[0], "max": values[-1]} if values else None,
            "abs_error": {
                "mean": sum(errors) / len(errors),
                "max": max(errors),
                "pairs": len(errors),
            }
            if errors
            else None,
        }
        if errors:
            note = (
                f"{len(errors)} pairs: |indicator - delivery| mean "
                f"{sum(errors) / len(errors):.3f}, max {max(errors):.3f}"
            )
            res.detail = f"{res.detail}; {note}" if res.detail else note
            self.say(f"      {note}")

    def _flaps(self, index: int, cond: Flaps, res: CheckResult) -> None:
        ref = _reference(self.sc.steps, index, cond.over)
        start, end = self.windows[ref]
        per = seconds(cond.per, self.sc.beacon)
        assert self.observer is not None
        stats = flaps(self.observer.samples, self.truth.states(), per=per, start=start, end=end)
        res.at = time.monotonic() - self.t0
        res.data = {"flaps": stats.to_json(), "over_step": ref}
        minutes = (end - start) / 60.0
        res.detail = (
            f"{stats.flaps} flaps among {stats.pairs} linked pairs in {minutes:.1f} min "
            f"({stats.samples} samples every {self.sc.sample:g} s); at most {stats.most} of one "
            f"pair within {per:g} s (allowed {cond.at_most})"
        )
        if stats.samples < 2:
            res.ok = False
            res.detail = f"fewer than 2 samples in the window of step {ref}: cannot tell"
        else:
            res.ok = stats.most <= cond.at_most
            if not res.ok:
                worst = ", ".join(
                    f"{a} dropped {b} {n} times (at "
                    + ", ".join(f"{t - start:.1f}" for t in stats.at[a][b][:5])
                    + " s)"
                    for a, b, n in stats.worst[:3]
                )
                res.detail += f"; worst: {worst}"
        self.say(f"{'ok   ' if res.ok else 'FAIL '} {res.description}: {res.detail}")

    def _resources(self, index: int, cond: Resources, res: CheckResult) -> None:
        ref = _reference(self.sc.steps, index, cond.over)
        res.at = time.monotonic() - self.t0
        before, after = self.usage.get(ref, ({}, {}))
        per = {
            r: procstat.window(before[r], after[r])
            for r in natural_order(list(before))
            if r in after and after[r].processes
        }
        if not per:
            res.detail = "no /proc readings of the daemons (lab without pids): not judged"
            self.say(f"skip  {res.description}: {res.detail}")
            return
        cpu = [u["cpu_percent"] for u in per.values()]
        pss = [u["pss_mib"] for u in per.values()]
        rss = [u["rss_mib"] for u in per.values()]
        wall = max(u["wall_s"] for u in per.values())
        res.data = {
            "over_step": ref,
            "daemons": len(per),
            "cpu_percent": {"mean": sum(cpu) / len(cpu), "max": max(cpu), "total": sum(cpu)},
            "pss_mib": {"mean": sum(pss) / len(pss), "max": max(pss), "total": sum(pss)},
            "rss_mib": {"mean": sum(rss) / len(rss), "max": max(rss)},
            "per_daemon": per,
        }
        res.detail = (
            f"{len(per)} daemons over {wall:.0f} s: CPU {sum(cpu) / len(cpu):.2f} % of one core "
            f"on average (max {max(cpu):.2f} %, all {sum(cpu):.0f} %); PSS "
            f"{sum(pss) / len(pss):.1f} MiB on average (max {max(pss):.1f}, all "
            f"{sum(pss):.0f} MiB), RSS {sum(rss) / len(rss):.1f} MiB"
        )
        over = []
        if cond.cpu_at_most is not None:
            over += [
                f"{r} used {u['cpu_percent']:.1f} % CPU"
                for r, u in per.items()
                if u["cpu_percent"] > cond.cpu_at_most
            ]
        if cond.pss_at_most is not None:
            over += [
                f"{r} took {u['pss_mib']:.1f} MiB"
                for r, u in per.items()
                if u["pss_mib"] > cond.pss_at_most
            ]
        res.ok = not over
        if over:
            res.detail += "; over the limit: " + ", ".join(over[:6])
        self.say(f"{'ok   ' if res.ok else 'FAIL '} {res.description}: {res.detail}")

    def _agreement(self, index: int, step: Check, cond: Agreement, res: CheckResult) -> None:
        ref = _reference(self.sc.steps, index, cond.over)
        start, end = self.windows[ref]
        lag = seconds(cond.lag, self.sc.beacon)
        loss_lag = seconds(cond.loss_lag, self.sc.beacon) if cond.loss_lag is not None else lag
        assert self.observer is not None
        stats = agreement(
            self.observer.samples,
            self.truth.states(),
            lag=lag,
            loss_lag=loss_lag,
            start=start,
            end=end,
        )
        value = stats.pair_share if cond.measure == "pairs" else stats.sample_share
        res.at = time.monotonic() - self.t0
        res.data = {
            "agreement": stats.to_json(),
            "lag_s": lag,
            "loss_lag_s": loss_lag,
            "over_step": ref,
        }
        other = stats.sample_share if cond.measure == "pairs" else stats.pair_share
        other_name = "samples fully agreeing" if cond.measure == "pairs" else "pairs agreeing"
        lags = f"lag {lag:g} s" + (f", {loss_lag:g} s for lost links" if loss_lag != lag else "")
        res.detail = (
            f"{value:.1%} of {cond.measure} agree over {stats.samples} samples of step {ref} "
            f"(target {cond.at_least:.0%}, {lags}; {other:.1%} {other_name}; wrong: "
            f"{stats.stale} stale, {stats.missing} missing)"
        )
        if stats.samples == 0:
            res.ok = False
            res.detail = (
                f"no samples in the window of step {ref} (observer every {self.sc.sample} s)"
            )
        else:
            res.ok = value >= cond.at_least
            if not res.ok and stats.worst:
                worst = ", ".join(
                    f"{a} on {b} wrong in {share:.0%} of samples" for a, b, share in stats.worst[:3]
                )
                res.detail += f"; worst: {worst}"
        self.say(f"{'ok   ' if res.ok else 'FAIL '} {res.description}: {res.detail}")

    # -- after the run -----------------------------------------------------------------------

    def _finish(self, result: RunResult, report: bool) -> None:
        records = None
        if self.captured and (self.pending or report):
            try:
                records = read_run(self.run_dir)
            except (NetlabError, OSError, ImportError) as exc:
                self.say(f"cannot read the captures: {exc}")
        for res, cond, since, until in self.pending:
            if records is None:
                res.detail = "captures could not be read: not judged"
                continue
            n = count_updates(records, since=since, until=until)
            res.ok = n <= cond.at_most
            res.detail = f"{n} Update datagrams in the window (at most {cond.at_most})"
            self._say(f"  {'ok   ' if res.ok else 'FAIL '} {res.description}: {res.detail}")
        if result.status == "passed" and any(c.ok is False for c in self.checks):
            result.status = "failed"
        lag = self._report_lag()
        meta = self._meta(result, lag)
        self._save_run(meta)
        if report:
            try:
                result.report = _write_report(
                    self.run_dir, records, self.samples, self.truth.states(), lag, meta
                )
            except (NetlabError, OSError, ImportError, ValueError) as exc:
                self._say(f"  report not written: {exc}")
        self._say("")
        for line in result.summary():
            self._say(line)
        files = "report.json and plots" if result.report is not None else "no report"
        kept = "pcaps, " if self.captured else ""
        self._say(f"run folder: {self.run_dir} ({files}; {kept}run.json, logs/)")

    def _report_lag(self) -> float:
        for step in self.sc.steps:
            if isinstance(step, Check) and isinstance(step.condition, Agreement):
                return seconds(step.condition.lag, self.sc.beacon)
        return self.sc.beacon

    def _meta(self, result: RunResult, lag: float) -> dict[str, Any]:
        steps = []
        for i, step in enumerate(self.sc.steps, 1):
            window = self.windows.get(i)
            steps.append(
                {
                    "step": i,
                    "kind": step.kind,
                    "label": step.label,
                    "start": window[0] if window else None,
                    "end": window[1] if window else None,
                }
            )
        return {
            "scenario": self.sc.name,
            "description": self.sc.description,
            "file": self.sc.source,
            "robots": len(self.sc.names),
            "beacon_interval_s": self.sc.beacon,
            "quick": self.quick,
            "status": result.status,
            "error": result.error,
            "start": self.wall[0],
            "end": self.wall[1],
            "agreement_lag_s": lag,
            "checks": [c.to_json() for c in self.checks],
            "steps": steps,
        }

    def _save_run(self, meta: Mapping[str, Any]) -> None:
        data = {
            "schema": RUN_SCHEMA,
            "meta": meta,
            "samples": [s.to_json() for s in self.samples],
            "truth": [s.to_json() for s in self.truth.states()],
        }
        tmp = self.run_dir / (RUN_JSON + ".tmp")
        tmp.write_text(json.dumps(data, indent=1) + "\n")
        tmp.replace(self.run_dir / RUN_JSON)


def _write_report(
    run_dir: Path,
    records: Any,
    samples: Sequence[Sample],
    truth: Sequence[TruthState],
    lag: float,
    meta: Mapping[str, Any],
) -> dict[str, Any]:
    from netlab.report import write_report

    stats = agreement(samples, truth, lag=lag)
    return write_report(
        run_dir,
        records=records if records is not None else [],
        connectivity_samples=connectivity(samples, truth) if samples else None,
        agreement_samples=stats.per_sample or None,
        meta=meta,
    )


def rebuild_report(run_dir: Path) -> dict[str, Any]:
    """Write ``report.json`` and the plots of a run folder again, from its pcaps and (when a
    scenario run made it) its ``run.json``."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise NetlabError(f"no run folder {run_dir}")
    saved = run_dir / RUN_JSON
    pcaps = sorted(run_dir.glob("*.pcap"))
    if not saved.exists() and not pcaps:
        raise NetlabError(f"{run_dir} has neither captures (*.pcap) nor {RUN_JSON}")
    if not saved.exists():
        from netlab.report import write_report

        return write_report(run_dir, records=None)
    try:
        data = json.loads(saved.read_text())
        meta = dict(data["meta"])
        samples = [Sample.from_json(s) for s in data.get("samples", [])]
        truth = [TruthState.from_json(s) for s in data.get("truth", [])]
        lag = float(meta.get("agreement_lag_s") or 0.0)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise NetlabError(f"{saved} is not a scenario run's record: {exc}") from None
    records = read_run(run_dir) if pcaps else []
    return _write_report(run_dir, records, samples, truth, lag, meta)
