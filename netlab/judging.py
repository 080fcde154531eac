"""Judging one snapshot of what the robots list: a list of problems ("r4 lists {r1, r2} but
should list {r1, r2, r3}"), empty when the condition holds.  Pure, so tested without root.

`PeerEntry` and `View` are what a robot lists (`netlab.observe.Probe` asks for them).
"""

from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from netlab.analysis import natural_order
from netlab.truth import Pair
from sdfr.records.schema import Neighbor, PeerJson

__all__ = [
    "MAX_PROBLEMS",
    "PeerEntry",
    "View",
    "address_problems",
    "expect_problems",
    "fmt_set",
    "history_problems",
    "indicator_problems",
    "unreachable_problems",
]

#: At most this many problems are spelled out in one message.
MAX_PROBLEMS = 6


@dataclass(frozen=True, slots=True)
class PeerEntry:
    """One entry of a neighbour list or history map."""

    robot_id: str
    reachable: bool
    address: str = ""
    services: frozenset[str] = frozenset()
    indicator: float | None = None

    @classmethod
    def of(cls, peer: Neighbor | PeerJson) -> PeerEntry:
        """The entry of a neighbour (``GET /neighbors``) or of a robot of the history map
        (``GET /history``), as the API's schema decodes them."""
        names = frozenset(s.name for s in peer.services)
        return cls(peer.robot_id, peer.reachable, peer.address, names, peer.indicator)


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
