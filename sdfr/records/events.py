"""Changes of what a robot knows, as the events of `GET /events`: pure, no I/O, no clock.

The discovery layer hands a `Tracker` every peer record it saves; the tracker says what changed
since that robot's record before: it appeared, left (Byebye), became unreachable (silence),
changed its services or its address, its connection indicator crossed a threshold, or was
forgotten. The API layer makes the events of this robot's own registrations (published,
unpublished, expired). Each process appends its events to the store's event log in the same
transaction as the change they describe, so an event is never told of a change that was not
stored, nor a stored change left untold (`sdfr.store`).
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from sdfr.records.model import PeerRecord, Service

#: Every kind of event, and what it means (the OpenAPI document and docs/api.md list these).
KINDS: dict[str, str] = {
    "robot.appeared": "a robot became reachable (`new`: never seen before)",
    "robot.left": "a reachable robot said goodbye (Byebye)",
    "robot.unreachable": "a reachable robot fell silent (or this robot's discovery restarted)",
    "robot.services": "a robot's services changed (`added`, `removed` ids, `changed`)",
    "robot.address": "a robot moved to another address",
    "robot.indicator": "a reachable robot's connection indicator crossed a threshold",
    "robot.forgotten": "a robot was dropped from the history map (it was full)",
    "service.published": "this robot published a service (or renewed its lease's ttl)",
    "service.unpublished": "this robot's service was unpublished",
    "service.expired": "this robot's service was withdrawn: its lease ran out",
    "resync": "the events since the asked id are no longer kept: read the state again",
}
#: Event families a filter may name: `robot` for every `robot.*` kind.
FAMILIES = frozenset(k.split(".")[0] for k in KINDS)
#: Indicator thresholds crossed upwards only once the indicator is this much above them: a
#: link that hovers at a threshold does not make an event every ping.
HYSTERESIS = 0.1
#: A services list larger than this in JSON is left out of an event (`services_truncated`):
#: the log stays small; `GET /neighbors` has the whole set.
MAX_SERVICES_JSON = 8192


@dataclass(frozen=True, slots=True)
class Event:
    """One change: its kind (see KINDS), the robot it is about (None: this robot), details."""

    kind: str
    robot_id: str | None = None
    data: dict[str, object] = field(default_factory=dict)

    def body(self, event_id: int, time: float) -> str:
        """The event's JSON as `GET /events` sends it in a `data:` line."""
        obj: dict[str, object] = {
            "id": event_id,
            "event": self.kind,
            "time": round(time, 6),
            "robot_id": self.robot_id,
        }
        obj.update((k, v) for k, v in self.data.items() if k not in obj)
        return json.dumps(obj, ensure_ascii=False, separators=(",", ":"))


def _services(services: Sequence[Service], key: str = "services") -> dict[str, object]:
    items = [s.to_json() for s in services]
    if len(json.dumps(items, ensure_ascii=False)) > MAX_SERVICES_JSON:
        return {f"{key}_truncated": True, f"{key}_count": len(items)}
    return {key: items}


def _band(thresholds: Sequence[float], indicator: float) -> int:
    return sum(1 for t in thresholds if indicator >= t)


class Tracker:
    """The discovery layer's memory of what it last saved of each robot, to tell changes."""

    def __init__(
        self,
        thresholds: Iterable[float] = (),
        known: Iterable[PeerRecord] = (),
        hysteresis: float = HYSTERESIS,
    ) -> None:
        self.thresholds = tuple(sorted(thresholds))
        self.hysteresis = hysteresis
        self._last: dict[str, PeerRecord] = {r.robot_id: r for r in known}
        #: Per reachable robot, the indicator band it was last told to be in.
        self._band: dict[str, int] = {}

    def observe(self, rec: PeerRecord) -> list[Event]:
        """What changed with this record of a robot since the last one seen."""
        before = self._last.get(rec.robot_id)
        self._last[rec.robot_id] = rec
        rid = rec.robot_id
        out: list[Event] = []
        was_reachable = before is not None and before.reachable
        if rec.reachable and not was_reachable:
            out.append(
                Event(
                    "robot.appeared",
                    rid,
                    {
                        "new": before is None,
                        "address": rec.address,
                        "indicator": rec.indicator,
                        **_services(rec.services),
                    },
                )
            )
            self._settle_band(rid, rec.indicator)
        elif before is not None and rec.services != before.services:
            out.append(Event("robot.services", rid, _diff(before.services, rec.services)))
        if before is not None and rec.address != before.address:
            out.append(
                Event("robot.address", rid, {"address": rec.address, "previous": before.address})
            )
        if rec.reachable and was_reachable:
            crossed = self._crossing(rid, rec.indicator)
            if crossed is not None:
                out.append(crossed)
        if was_reachable and not rec.reachable:
            self._band.pop(rid, None)
            kind = "robot.left" if rec.departed else "robot.unreachable"
            out.append(Event(kind, rid, {"address": rec.address, "last_seen": rec.last_seen}))
        return out

    def checkpoint(self) -> tuple[dict[str, PeerRecord], dict[str, int]]:
        """What `rollback` needs to undo the observations made after this call."""
        return dict(self._last), dict(self._band)

    def rollback(self, saved: tuple[dict[str, PeerRecord], dict[str, int]]) -> None:
        """Forget the observations made since `checkpoint` (they were not saved)."""
        self._last, self._band = dict(saved[0]), dict(saved[1])

    def forget(self, robot_id: str) -> Event:
        """The robot was dropped from the history map."""
        self._last.pop(robot_id, None)
        self._band.pop(robot_id, None)
        return Event("robot.forgotten", robot_id)

    def _settle_band(self, robot_id: str, indicator: float | None) -> None:
        if indicator is None:
            self._band.pop(robot_id, None)
        else:
            self._band[robot_id] = _band(self.thresholds, indicator)

    def _crossing(self, robot_id: str, indicator: float | None) -> Event | None:
        if indicator is None or not self.thresholds:
            return None
        band = self._band.get(robot_id)
        if band is None:  # its first settled ping: the appeared event told the start
            self._band[robot_id] = _band(self.thresholds, indicator)
            return None
        now = _band(self.thresholds, indicator)
        if now < band:
            threshold = self.thresholds[now]  # the lowest one it fell below
            direction = "down"
        elif now > band:
            # Up only once clear of the threshold by the hysteresis.
            now = _band(self.thresholds, indicator - self.hysteresis)
            if now <= band:
                return None
            threshold = self.thresholds[now - 1]
            direction = "up"
        else:
            return None
        self._band[robot_id] = now
        return Event(
            "robot.indicator",
            robot_id,
            {"indicator": indicator, "threshold": threshold, "direction": direction},
        )


def _diff(before: Sequence[Service], after: Sequence[Service]) -> dict[str, object]:
    old = {s.id: s for s in before}
    new = {s.id: s for s in after}
    added = [s for sid, s in new.items() if sid not in old]
    changed = [s for sid, s in new.items() if sid in old and old[sid] != s]
    removed = [sid for sid in old if sid not in new]
    return {**_services(added, "added"), "removed": removed, **_services(changed, "changed")}


# -- this robot's registrations (the API layer) --------------------------------------------------


def published(service: Service, ttl: float | None, expires: float | None) -> Event:
    return Event(
        "service.published",
        None,
        {"service_id": service.id, "service": service.to_json(), "ttl": ttl, "expires": expires},
    )


def unpublished(service_id: str) -> Event:
    return Event("service.unpublished", None, {"service_id": service_id})


def expired(service: Service) -> Event:
    return Event("service.expired", None, {"service_id": service.id, "service": service.to_json()})


def unreachable_at_start(records: Iterable[PeerRecord]) -> list[Event]:
    """The discovery layer starts knowing nobody reachable: robots the last run listed are
    told unreachable, so that a consumer's view matches the daemon's."""
    return [
        Event(
            "robot.unreachable",
            r.robot_id,
            {"address": r.address, "last_seen": r.last_seen, "reason": "discovery restarted"},
        )
        for r in records
        if r.reachable
    ]


def kind_filter(names: Iterable[str]) -> frozenset[str]:
    """The kinds a filter selects: kinds by name, or families (`robot`) for all of theirs;
    ValueError naming what is neither."""
    out: set[str] = set()
    for name in names:
        if name in KINDS:
            out.add(name)
        elif name in FAMILIES:
            out.update(k for k in KINDS if k.startswith(name + "."))
        else:
            known = ", ".join([*sorted(FAMILIES), *KINDS])
            raise ValueError(f"{name!r} is no event kind or family (known: {known})")
    return frozenset(out)
