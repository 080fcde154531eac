"""What a scenario is written with: its errors, durations, robot selectors and value checks.

Every other module of the package builds on these; none of it runs anything.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from netlab.errors import NetlabError
from netlab.judging import fmt_set

#: Names a selector may use besides robots and groups.
KEYWORDS = ("all", "running")
#: sdfrd options the lab sets itself.
RESERVED_OPTIONS = ("iface", "fleet", "robot_id", "state_dir", "beacon_interval", "addressing")


class ScenarioError(NetlabError, ValueError):
    """A scenario (file or objects) is not valid; the message names the step and the field."""


class StepError(NetlabError):
    """A step could not be carried out on this lab."""


class Bad(ValueError):
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
    def of(cls, value: object) -> Duration:
        """From a Duration, a number of seconds, or text: "2 s", "500 ms", "3 beacons",
        "2 min", "1 beacon + 1 s"; ValueError saying what is accepted otherwise."""
        if isinstance(value, Duration):
            return value
        if isinstance(value, bool) or not isinstance(value, int | float | str):
            raise Bad(f"expected seconds or text like '3 beacons', got {value!r}")
        if not isinstance(value, str):
            seconds = float(value)
            if not (math.isfinite(seconds) and seconds >= 0):
                raise Bad(f"must be a finite number of seconds >= 0, got {value!r}")
            return cls(seconds)
        secs = beacons = 0.0
        for term in value.split("+"):
            m = _TERM_RE.match(term)
            if m is None:
                raise Bad(
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
class Selectors:
    """What a scenario's steps are checked against: its robots and groups."""

    names: tuple[str, ...]
    groups: Mapping[str, tuple[str, ...]]

    def robots(self, sel: Robots, running: Iterable[str] | None = None) -> tuple[str, ...]:
        """The robots `sel` names, in order; "running" is every robot when `running` is None."""
        items = [sel] if isinstance(sel, str) else list(sel)
        if not items:
            raise Bad("names no robot (an empty list)")
        out: list[str] = []
        for item in items:
            if not isinstance(item, str):
                raise Bad(f"expected robot or group names, got {item!r}")
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
                raise Bad(
                    f"unknown robot or group {item!r} (robots: {names_text(self.names)}"
                    f"{groups}; or 'all', 'running')"
                )
        return tuple(dict.fromkeys(out))

    def robot(self, name: str) -> str:
        if not isinstance(name, str) or name not in self.names:
            raise Bad(f"unknown robot {name!r} (robots: {names_text(self.names)})")
        return name


def names_text(names: Sequence[str]) -> str:
    """``r1..r6`` for a default fleet, else the names."""
    if len(names) > 2 and list(names) == [f"r{i}" for i in range(1, len(names) + 1)]:
        return f"r1..r{len(names)}"
    return ", ".join(names)


def sel_text(sel: Robots | None, default: str = "every robot") -> str:
    if sel is None:
        return default
    if isinstance(sel, str):
        return {"all": "all robots", "running": "all running robots"}.get(sel, sel)
    return fmt_set(sel)


def check_field(name: str, check: Callable[[], object]) -> None:
    try:
        check()
    except Bad as exc:
        raise Bad(f"{name}: {exc}") from None


def bounded(value: object, what: str, low: float = -math.inf, high: float = math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise Bad(f"{what}: expected a number, got {value!r}")
    if not (math.isfinite(value) and low <= value <= high):
        rng = f">= {low:g}" if high == math.inf else f"{low:g}-{high:g}"
        raise Bad(f"{what}: must be {rng}, got {value!r}")
    return float(value)


def min_max(value: object, what: str, low: float) -> None:
    if not (isinstance(value, Sequence) and len(value) == 2):
        raise Bad(f"{what}: expected (min, max), got {value!r}")
    a = bounded(value[0], what, low)
    b = bounded(value[1], what, low)
    if a > b:
        raise Bad(f"{what}: min {a:g} is above max {b:g}")


def whole(value: object, what: str) -> None:
    if isinstance(value, bool) or not isinstance(value, int):
        raise Bad(f"{what}: expected a whole number, got {value!r}")
    if value < 0:
        raise Bad(f"{what}: must be >= 0, got {value}")


def area_size(value: object, what: str) -> None:
    if not (isinstance(value, Sequence) and len(value) == 2):
        raise Bad(f"{what}: expected (width, height) in metres, got {value!r}")
    bounded(value[0], what, 0.001)
    bounded(value[1], what, 0.001)


def boolean(value: object) -> bool:
    if not isinstance(value, bool):
        raise Bad(f"expected true or false, got {value!r}")
    return value


def select_groups(selectors: Selectors, groups: Sequence[Robots]) -> list[tuple[str, ...]]:
    if isinstance(groups, str) or not isinstance(groups, Sequence) or not groups:
        raise Bad(f"expected a list of groups, got {groups!r}")
    out = [selectors.robots(g) for g in groups]
    seen: set[str] = set()
    for g in out:
        if seen & set(g):
            raise Bad(f"robots in more than one group: {fmt_set(seen & set(g))}")
        seen |= set(g)
    return out


def check_options(options: Mapping[str, Any]) -> None:
    if not isinstance(options, Mapping):
        raise Bad(f"expected a table of sdfrd options, got {options!r}")
    for key, value in options.items():
        if not isinstance(key, str) or not re.fullmatch(r"[a-z][a-z0-9_]*", key):
            raise Bad(f"{key!r} is not an sdfrd option name (like miss_limit)")
        if key in RESERVED_OPTIONS:
            what = {"beacon_interval": "beacon", "addressing": "addressing"}.get(key)
            where = f"the scenario's {what}" if what else "the lab"
            raise Bad(f"{key} is set by {where}")
        if isinstance(value, bool) or not isinstance(value, str | int | float):
            raise Bad(f"{key}: expected a string or a number, got {value!r}")


def pairs_of(robots: Sequence[str], peers: Sequence[str], *, both: bool) -> list[tuple[str, str]]:
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


# ---------------------------------------------------------------------------------------------
# Values as a scenario file writes them (TOML): each converter raises Bad saying what it wants.
# `netlab.scenario.files` picks one per field from the field's type, or from `toml(...)` in
# the field's metadata where the file writes it differently.

Conv = Callable[[object], object]
TOML = "netlab.toml"


@dataclass(frozen=True, slots=True)
class Spread:
    """Field metadata: the field is a table gathered from these keys of the step's own table
    (Shape's parameters are written ``delay = 50`` beside ``shape = "r1"``)."""

    keys: Callable[[], Sequence[str]]


def toml(conv: Conv | Spread) -> dict[str, Conv | Spread]:
    """Field metadata: read this field from a file with `conv`, not by its type."""
    return {TOML: conv}


def to_str(v: object) -> str:
    if not isinstance(v, str):
        raise Bad(f"expected text, got {v!r}")
    return v


def to_int(v: object) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise Bad(f"expected a whole number, got {v!r}")
    return v


def to_float(v: object) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise Bad(f"expected a number, got {v!r}")
    return float(v)


def to_robots(v: object) -> Robots:
    if v is True:
        return "all"
    if isinstance(v, str):
        return v
    if isinstance(v, list) and v and all(isinstance(x, str) for x in v):
        return tuple(v)
    raise Bad(f"expected a robot, a group, 'all' or a list of these, got {v!r}")


def to_groups(v: object) -> tuple[Robots, ...]:
    if not isinstance(v, list) or not v:
        raise Bad(f"expected a list of groups (group names, or lists of robots), got {v!r}")
    return tuple(to_robots(g) for g in v)


def to_pair(v: object) -> tuple[float, float]:
    if not (isinstance(v, list) and len(v) == 2):
        raise Bad(f"expected [x, y], got {v!r}")
    return (to_float(v[0]), to_float(v[1]))


def to_range(v: object) -> tuple[float, float]:
    """[min, max], or one number for both."""
    if isinstance(v, int | float) and not isinstance(v, bool):
        return (float(v), float(v))
    if not (isinstance(v, list) and len(v) == 2):
        raise Bad(f"expected [min, max] or a number, got {v!r}")
    return (to_float(v[0]), to_float(v[1]))


def to_table(v: object) -> dict[str, object]:
    if not isinstance(v, dict):
        raise Bad(f"expected a table, got {v!r}")
    return dict(v)


def to_loss(v: object) -> float | None:
    if v == "none":
        return None
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise Bad(f"expected a loss in % or 'none' (back to the range model), got {v!r}")
    return float(v)


def to_true(v: object) -> bool:
    if v is not True:
        raise Bad(f"write `= true`, got {v!r}")
    return True


def to_placed(v: object) -> tuple[str, ...]:
    """A host's robots in [hosts]: a robot or group, or a list of them (empty: a share of the
    robots no host names)."""
    if isinstance(v, str):
        return (v,)
    if isinstance(v, list) and all(isinstance(x, str) for x in v):
        return tuple(v)
    raise Bad(f"expected a robot, a group or a list of them (or [] for a share), got {v!r}")


def to_names(v: object) -> tuple[str, ...]:
    if not (isinstance(v, list) and all(isinstance(x, str) for x in v)):
        raise Bad(f"expected a list of robot names, got {v!r}")
    return tuple(v)
