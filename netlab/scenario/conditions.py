"""Conditions: what a check waits for, or judges once over what the run gathered.

A condition is a frozen dataclass with a `kind` (its name in scenario files), its fields
(the file's keys, with their defaults), `describe()` and `_validate()`.  How the engine
evaluates it lives in `netlab.scenario.judges`, registered under the same class.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

from netlab.scenario.spec import (
    Bad,
    Duration,
    Robots,
    Selectors,
    Span,
    boolean,
    bounded,
    check_field,
    sel_text,
    select_groups,
    whole,
)


@dataclass(frozen=True)
class Condition:
    """What a `Check` looks at."""

    kind: ClassVar[str] = "condition"
    #: Polled until it holds (False: judged once over data already gathered).
    polled: ClassVar[bool] = True
    #: Fields naming an earlier step (a label or a kind; None: the last action step).
    refers_to: ClassVar[tuple[str, ...]] = ()

    def describe(self) -> str:
        return self.kind

    def _validate(self, selectors: Selectors) -> None:
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
            parts = " | ".join(sel_text(g) for g in self.groups)
            return f"{parts}: each lists {'only ' if self.exact else ''}its group{tail}"
        who = sel_text(self.robots, "all running robots")
        return f"{who} list each other{tail}"

    def _validate(self, selectors: Selectors) -> None:
        if self.robots is not None and self.groups is not None:
            raise Bad("give robots (one group) or groups (several), not both")
        if self.robots is not None:
            check_field("robots", lambda: selectors.robots(self.robots or ()))
        if self.groups is not None:
            check_field("groups", lambda: select_groups(selectors, self.groups or ()))
        check_field("services", lambda: boolean(self.services))
        check_field("exact", lambda: boolean(self.exact))


@dataclass(frozen=True)
class Medium(Condition):
    """Each running robot of `robots` lists as reachable exactly the running robots the medium
    links it to now (the ground truth), with their services if `services`."""

    robots: Robots = "running"
    services: bool = False
    kind: ClassVar[str] = "medium"

    def describe(self) -> str:
        who = sel_text(self.robots)
        return f"{who} list exactly whom the medium links them to"

    def _validate(self, selectors: Selectors) -> None:
        check_field("robots", lambda: selectors.robots(self.robots))
        check_field("services", lambda: boolean(self.services))


@dataclass(frozen=True)
class Unreachable(Condition):
    """No robot of `on` (default: every other running robot) lists any of `robots` as
    reachable."""

    robots: Robots
    on: Robots | None = None
    kind: ClassVar[str] = "unreachable"

    def describe(self) -> str:
        return f"{sel_text(self.robots)} unreachable on {sel_text(self.on, 'every peer')}"

    def _validate(self, selectors: Selectors) -> None:
        check_field("robots", lambda: selectors.robots(self.robots))
        if self.on is not None:
            check_field("on", lambda: selectors.robots(self.on or ()))


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
        return f"{sel_text(self.robots)} in the history of {sel_text(self.on, 'every peer')}" + (
            state + fell
        )

    def _validate(self, selectors: Selectors) -> None:
        check_field("robots", lambda: selectors.robots(self.robots))
        if self.on is not None:
            check_field("on", lambda: selectors.robots(self.on or ()))
        if self.reachable is not None:
            check_field("reachable", lambda: boolean(self.reachable))
        if self.indicator_below is not None:
            bounded(self.indicator_below, "indicator_below", 0.0, 1.0)
        check_field("falling", lambda: boolean(self.falling))


@dataclass(frozen=True)
class DistinctAddresses(Condition):
    """No two robots are listed at the same address by `robots` (an address collision was
    resolved).  Meaningful with sdfrd's address self-configuration (``--addressing auto``)."""

    robots: Robots = "running"
    kind: ClassVar[str] = "addresses"

    def describe(self) -> str:
        return f"{sel_text(self.robots)}: every robot at its own address"

    def _validate(self, selectors: Selectors) -> None:
        check_field("robots", lambda: selectors.robots(self.robots))


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
    refers_to: ClassVar[tuple[str, ...]] = ("over",)

    def describe(self) -> str:
        over = f" over {self.over}" if self.over else ""
        loss = f", {Duration.of(self.loss_lag)} for lost links" if self.loss_lag is not None else ""
        return (
            f"lists agree with the medium >= {self.at_least:.0%} of {self.measure}{over} "
            f"(lag {Duration.of(self.lag)}{loss})"
        )

    def _validate(self, selectors: Selectors) -> None:
        bounded(self.at_least, "at_least", 0.0, 1.0)
        check_field("lag", lambda: Duration.of(self.lag))
        if self.loss_lag is not None:
            check_field("loss_lag", lambda: Duration.of(self.loss_lag or 0))
        if self.measure not in MEASURES:
            raise Bad(f"measure: one of {', '.join(MEASURES)}, got {self.measure!r}")


@dataclass(frozen=True)
class Updates(Condition):
    """At most `at_most` Update datagrams went on the air from the start of step `after` (a
    label or a step kind; default: the last action step) to this check: services are not
    re-fetched when unchanged.  Counted from the captures at the end of the run."""

    at_most: int = 0
    after: str | None = None
    kind: ClassVar[str] = "updates"
    polled: ClassVar[bool] = False
    refers_to: ClassVar[tuple[str, ...]] = ("after",)

    def describe(self) -> str:
        return f"at most {self.at_most} Update datagrams since {self.after or 'the last step'}"

    def _validate(self, selectors: Selectors) -> None:
        whole(self.at_most, "at_most")


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
    refers_to: ClassVar[tuple[str, ...]] = ("over",)

    def describe(self) -> str:
        over = f" over {self.over}" if self.over else ""
        return f"no peer flaps out more than {self.at_most} per {Duration.of(self.per)}{over}"

    def _validate(self, selectors: Selectors) -> None:
        whole(self.at_most, "at_most")
        check_field("per", lambda: Duration.of(self.per))


@dataclass(frozen=True)
class Indicator(Condition):
    """Each running robot of `robots` rates every peer it lists within `tolerance` (0-1) of
    the share of pings the medium lets come back: (1 - loss there) x (1 - loss back)."""

    robots: Robots = "running"
    tolerance: float = 0.15
    kind: ClassVar[str] = "indicator"

    def describe(self) -> str:
        return (
            f"{sel_text(self.robots)}: indicators within {self.tolerance * 100:g} points of "
            "the medium's round-trip delivery"
        )

    def _validate(self, selectors: Selectors) -> None:
        check_field("robots", lambda: selectors.robots(self.robots))
        bounded(self.tolerance, "tolerance", 0.0, 1.0)


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
    refers_to: ClassVar[tuple[str, ...]] = ("over",)

    def describe(self) -> str:
        limits = []
        if self.cpu_at_most is not None:
            limits.append(f"CPU <= {self.cpu_at_most:g} %")
        if self.pss_at_most is not None:
            limits.append(f"PSS <= {self.pss_at_most:g} MiB")
        over = f" over {self.over}" if self.over else ""
        return f"CPU and memory per daemon{over}" + (f": {', '.join(limits)}" if limits else "")

    def _validate(self, selectors: Selectors) -> None:
        if self.cpu_at_most is not None:
            bounded(self.cpu_at_most, "cpu_at_most", 0.0)
        if self.pss_at_most is not None:
            bounded(self.pss_at_most, "pss_at_most", 0.0)


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
