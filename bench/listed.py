"""What the side-by-side makes of its watchers' notes, as pure functions: what each robot listed
at a moment (its seen/gone events replayed), what a robot had published, and when a condition
on what every robot lists first held.  The same for every system, since every system's node
writes the same events (`bench.peer_node`, `bench.paper_load`)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any

Listed = dict[str, set[tuple[str, str]]]


def replay(events: Iterable[dict[str, Any]], until: float) -> Listed:
    """What each watcher listed at `until`, from its seen/gone events."""
    listed: Listed = {}
    for e in events:
        if float(e["t"]) > until:
            break
        _apply(listed, e)
    return listed


def _apply(listed: Listed, e: dict[str, Any]) -> bool:
    """A seen or gone event applied to what each watcher lists; False for any other event."""
    if e["op"] not in ("seen", "gone"):
        return False
    s = listed.setdefault(str(e["at"]), set())
    item = (str(e["robot"]), str(e["sid"]))
    (s.add if e["op"] == "seen" else s.discard)(item)
    return True


def first_time(
    events: Sequence[dict[str, Any]],
    since: float,
    until: float,
    holds: Callable[[Listed], bool],
) -> float | None:
    """Seconds from `since` until `holds(listed)` first holds (None: not before `until`)."""
    listed: Listed = {}
    checked = False
    for e in events:
        t = float(e["t"])
        if t > until:
            break
        if t >= since and not checked:
            checked = True
            if holds(listed):
                return 0.0
        if _apply(listed, e) and t >= since and holds(listed):
            return round(t - since, 3)
    if not checked and holds(listed):
        return 0.0
    return None


def own_services(events: Sequence[dict[str, Any]], robot: str, until: float) -> set[str]:
    """The services `robot` had published at `until`, by its publish/unpublish notes."""
    up: set[str] = set()
    for e in events:
        if float(e["t"]) > until:
            break
        if e.get("robot") == robot and e["op"] == "publish":
            up.add(str(e["sid"]))
        elif e.get("robot") == robot and e["op"] == "unpublish":
            up.discard(str(e["sid"]))
    return up


def everyone_lists(
    watchers: Sequence[str], wanted: dict[str, set[str]], exact: bool = False
) -> Callable[[Listed], bool]:
    """Every watcher lists every wanted (robot, sid) of the other robots (`exact`: and
    nothing else)."""

    def holds(listed: Listed) -> bool:
        for w in watchers:
            want = {(r, s) for r, sids in wanted.items() if r != w for s in sids}
            have = listed.get(w, set())
            if (have != want) if exact else not want <= have:
                return False
        return True

    return holds


def everyone_lists_one(
    watchers: Sequence[str], robot: str, prefixes: tuple[str, ...]
) -> Callable[[Listed], bool]:
    """Every watcher lists a service of `robot` whose id starts with one of `prefixes`."""

    def holds(listed: Listed) -> bool:
        return all(
            any(r == robot and sid.startswith(prefixes) for r, sid in listed.get(w, set()))
            for w in watchers
        )

    return holds


def nobody_lists_these(
    watchers: Sequence[str], robot: str, sids: set[str]
) -> Callable[[Listed], bool]:
    """No watcher lists any of these services of `robot`."""

    def holds(listed: Listed) -> bool:
        return all(
            not (r == robot and s in sids) for w in watchers for r, s in listed.get(w, set())
        )

    return holds


def nobody_lists(watchers: Sequence[str], robots: Sequence[str]) -> Callable[[Listed], bool]:
    def holds(listed: Listed) -> bool:
        return all(r not in robots for w in watchers for r, _ in listed.get(w, set()))

    return holds


def halves_apart(a: Sequence[str], b: Sequence[str]) -> Callable[[Listed], bool]:
    def holds(listed: Listed) -> bool:
        return nobody_lists(a, b)(listed) and nobody_lists(b, a)(listed)

    return holds
