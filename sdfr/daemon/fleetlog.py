"""The fleet's changes as this robot sees them, one info line each, for whoever reads the log
after the fact: a robot appeared, became unreachable, came back, left, changed its services or
its address, was forgotten.

What changed is told by `events.Tracker` (the same rules as `GET /events`), from the records
the discovery layer takes from the protocol core: only robots that proved themselves (answered
a ping of ours) ever get there, so a flood of forged robot ids is not logged. A fleet that
changes faster than BURST lines at once, then RATE a second, has the rest counted, and said in
one line now and then (SUMMARY_EVERY), by kind.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Iterable, Sequence

from sdfr.daemon.logs import FIELDS
from sdfr.protocol.limits import TokenBucket
from sdfr.records import events
from sdfr.records.model import CONTROL_RE, PeerRecord, Service

log = logging.getLogger("sdfrd.fleet")

#: Lines at once before the rate limit: the merge of a fleet of a hundred says every robot.
BURST = 200
#: Lines a second once the burst is spent.
RATE = 2.0
#: Seconds between two lines that count what was held back.
SUMMARY_EVERY = 10.0
#: Service names a line lists before "and N more".
NAMES_SHOWN = 8


def duration(seconds: float) -> str:
    """A span of time as a person reads it: 0.8 s, 42 s, 12 min, 3.5 h, 2 d."""
    if seconds < 10:
        return f"{max(seconds, 0.0):.1f} s"
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    if seconds < 172800:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.0f} d"


def _names(services: Iterable[Service]) -> list[str]:
    return [CONTROL_RE.sub("?", s.name) for s in services]


def _listed(names: Sequence[str]) -> str:
    shown = ", ".join(names[:NAMES_SHOWN])
    more = len(names) - NAMES_SHOWN
    return f"{shown} and {more} more" if more > 0 else shown


class FleetLog:
    """Says each change of the robots this robot knows, at a bounded rate (see the module)."""

    def __init__(
        self,
        known: Iterable[PeerRecord] = (),
        *,
        burst: int = BURST,
        rate: float = RATE,
        summary_every: float = SUMMARY_EVERY,
        logger: logging.Logger = log,
    ) -> None:
        """`known`: the robots of the history map, on the core's clock, none reachable yet."""
        known = list(known)
        self.tracker = events.Tracker((), known)
        #: Each robot's record as last observed (what a change is told against).
        self._last: dict[str, PeerRecord] = {r.robot_id: r for r in known}
        self.burst = burst
        self.rate = rate
        self.summary_every = summary_every
        self.logger = logger
        self._lines = TokenBucket(rate, burst)
        self._held: Counter[str] = Counter()
        self._summarised: float | None = None

    def observe(self, removed: Sequence[str], records: Sequence[PeerRecord], now: float) -> None:
        """The core's changes (`Core.take_removed`, `Core.take_dirty`) at `now` (its clock)."""
        for robot_id in removed:
            if self._last.pop(robot_id, None) is not None:
                self.tracker.forget(robot_id)
                self._say(
                    now,
                    f"robot {robot_id} forgotten: the history map is full",
                    {"robot": robot_id, "event": "forgotten"},
                )
        for rec in records:
            before = self._last.get(rec.robot_id)
            self._last[rec.robot_id] = rec
            for event in self.tracker.observe(rec):
                self._tell(event, before, rec, now)

    def tick(self, now: float) -> None:
        """Say what was held back, if it is time (the discovery layer's periodic tick)."""
        self._summary(now)

    # -- the lines -----------------------------------------------------------------------

    def _tell(
        self, event: events.Event, before: PeerRecord | None, rec: PeerRecord, now: float
    ) -> None:
        rid, address = rec.robot_id, rec.address
        fields: dict[str, object] = {"robot": rid, "address": address}
        if event.kind == "robot.appeared":
            names = _names(rec.services)
            with_services = f", services: {_listed(names)}" if names else ""
            if before is None:
                text = f"robot {rid} appeared at {address} (first seen){with_services}"
                fields.update(event="appeared")
            else:
                away = rec.last_seen - before.last_seen
                text = f"robot {rid} came back at {address} after {duration(away)}{with_services}"
                fields.update(event="came_back", away_s=round(away, 3))
            fields.update(version=rec.version, services=names)
        elif event.kind == "robot.unreachable":
            silent = now - rec.last_seen
            text = f"robot {rid} unreachable: silent for {duration(silent)} (was at {address})"
            fields.update(event="unreachable", silent_s=round(silent, 3))
        elif event.kind == "robot.left":
            text = f"robot {rid} left (said byebye) from {address}"
            fields.update(event="left")
        elif event.kind == "robot.services":
            text, changes = self._services_changed(before, rec)
            fields.update(event="services", version=rec.version, **changes)
        elif event.kind == "robot.address":
            previous = before.address if before is not None else "?"
            text = f"robot {rid} moved from {previous} to {address}"
            fields.update(event="address", previous=previous)
        else:  # (no other kind is made for a record: indicator crossings are not tracked)
            return
        self._say(now, text, fields)

    @staticmethod
    def _services_changed(
        before: PeerRecord | None, rec: PeerRecord
    ) -> tuple[str, dict[str, list[str]]]:
        old = {s.id: s for s in (before.services if before is not None else ())}
        new = {s.id: s for s in rec.services}
        changes = {
            "added": _names(s for sid, s in new.items() if sid not in old),
            "removed": _names(s for sid, s in old.items() if sid not in new),
            "changed": _names(s for sid, s in new.items() if sid in old and old[sid] != s),
        }
        said = "; ".join(f"{k} {_listed(v)}" for k, v in changes.items() if v)
        return f"robot {rec.robot_id} services now version {rec.version}: {said}", changes

    # -- the rate bound ------------------------------------------------------------------

    def _say(self, now: float, text: str, fields: dict[str, object]) -> None:
        if not self._lines.take(now):
            self._held[str(fields["event"])] += 1
            return
        self._summary(now)
        self.logger.info(text, extra={FIELDS: fields})

    def _summary(self, now: float) -> None:
        if not self._held:
            return
        if self._summarised is not None and now - self._summarised < self.summary_every:
            return
        held, self._held = self._held, Counter()
        self._summarised = now
        total = sum(held.values())
        kinds = ", ".join(f"{n} {kind}" for kind, n in held.most_common())
        self.logger.info(
            f"{total} more fleet changes not logged ({kinds}): more than {self.burst} at once, "
            f"then {self.rate:g} a second, are counted only; GET /events has every one",
            extra={FIELDS: {"event": "suppressed", "suppressed": dict(held)}},
        )
