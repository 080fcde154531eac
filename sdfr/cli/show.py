"""What `sdfr` prints: aligned tables, avahi-browse-like parsable lines, and one line per change
(with the names of services, remembered from what the command saw)."""

from __future__ import annotations

import time
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from sdfr.client import Change
from sdfr.records.model import attr_text

Row = Sequence[object]


def table(headers: Sequence[str], rows: Sequence[Row]) -> str:
    """Columns aligned, two spaces apart."""
    cells = [[str(c) for c in headers], *[[_cell(c) for c in row] for row in rows]]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in cells]
    return "\n".join(lines)


def _cell(value: object) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    return str(value)


def _indicator(value: object) -> str:
    return f"{value:.2f}" if isinstance(value, int | float) else "-"


def _rtt(value: object) -> str:
    return f"{value:.1f} ms" if isinstance(value, int | float) else "-"


def _ago(epoch: object, now: float) -> str:
    if not isinstance(epoch, int | float) or epoch <= 0:
        return "-"
    age = max(0.0, now - epoch)
    if age < 120:
        return f"{age:.0f}s ago"
    if age < 7200:
        return f"{age / 60:.0f}m ago"
    return f"{age / 3600:.1f}h ago"


def names(services: list[dict[str, Any]], limit: int = 4) -> str:
    names = [str(s.get("name")) for s in services]
    if len(names) > limit:
        return ", ".join(names[:limit]) + f", +{len(names) - limit} more"
    return ", ".join(names) or "-"


def attrs_text(attributes: object) -> str:
    if not isinstance(attributes, dict) or not attributes:
        return "-"
    return " ".join(f"{k}={attr_text(v)}" for k, v in attributes.items())


def show_neighbors(answer: dict[str, Any]) -> str:
    return _robots(answer["neighbors"], "no reachable robots")


def show_services(answer: dict[str, Any]) -> str:
    services = answer["services"]
    if not services:
        return "no services published"
    return table(
        ["ID", "NAME", "TYPE", "URL", "ATTRIBUTES", "LEASE"],
        [
            (
                s["id"],
                s["name"],
                s["type"],
                s["url"],
                attrs_text(s.get("attributes")),
                f"{s['ttl']:g} s" if isinstance(s.get("ttl"), int | float) else "-",
            )
            for s in services
        ],
    )


def show_history(answer: dict[str, Any]) -> str:
    return _robots(answer["robots"], "no robot seen yet", time.time())


def _robots(robots: list[dict[str, Any]], empty: str, now: float | None = None) -> str:
    """The neighbours' table; given `now`, the history's (with a LAST SEEN column)."""
    if not robots:
        return empty
    headers = ["ROBOT", "ADDRESS", "REACHABLE", "INDICATOR", "RTT", "SERVICES"]
    if now is not None:
        headers.insert(3, "LAST SEEN")
    rows = []
    for r in robots:
        row = [r["robot_id"], r["address"] or "-", r["reachable"], _indicator(r.get("indicator"))]
        row += [_rtt(r.get("rtt_ms")), names(r["services"])]
        if now is not None:
            row.insert(3, _ago(r.get("last_seen"), now))
        rows.append(row)
    return table(headers, rows)


def show_self(answer: dict[str, Any]) -> str:
    disc = answer.get("discovery") or {}
    state = "up" if disc.get("up") else "down"
    age = disc.get("heartbeat_age")
    if isinstance(age, int | float):
        state += f" (last heartbeat {age:.1f}s ago)"
    pairs = [
        ("robot", answer.get("robot_id")),
        ("fleet", answer.get("fleet")),
        ("address", answer.get("address") or None),
        ("boot id", answer.get("boot_id")),
        ("version", answer.get("version")),
        ("location", answer.get("location")),
        ("discovery", state),
    ]
    lines = [f"{key + ':':<10} {_cell(value)}" for key, value in pairs]
    return "\n".join(lines) + "\n\n" + show_services(answer)


def show_health(answer: Mapping[str, Any]) -> str:
    age = answer.get("discovery_heartbeat_age")
    beat = f", last heartbeat {age:.1f}s ago" if isinstance(age, int | float) else ""
    auth = f", fleet key: {answer['auth']}" if answer.get("auth") else ""
    lines = [
        f"{answer['status']}: api {answer['api']}, discovery {answer['discovery']}{beat}{auth}"
    ]
    if answer.get("discovery_error"):
        lines.append(f"error: {answer['discovery_error']}")
    lines += [f"warning: {w}" for w in answer.get("warnings") or []]
    return "\n".join(lines)


# -- parsable lines (search --parsable) ----------------------------------------------------------


def escape(text: str) -> str:
    """A field of a parsable line: ';', '\\' and control characters as \\DDD (their decimal
    code, three digits), as avahi-browse -p writes them."""
    return "".join(
        f"\\{ord(c):03d}" if c in ";\\" or ord(c) < 32 or ord(c) == 127 else c for c in text
    )


def parsable(answer: Mapping[str, Any]) -> str:
    """One line per service: =;ROBOT;ADDRESS;ID;NAME;TYPE;URL;KEY=VALUE;..."""
    lines = []
    for robot in answer["neighbors"]:
        for s in robot["services"]:
            fields = [robot["robot_id"], robot["address"] or "", s["id"], s["name"], s["type"]]
            fields.append(s.get("url") or "")
            attrs = s.get("attributes") or {}
            fields += [f"{k}={attr_text(v)}" for k, v in attrs.items()]
            lines.append(";".join(["=", *map(escape, fields)]))
    return "\n".join(lines)


# -- changes -------------------------------------------------------------------------------------


def _clock(epoch: float) -> str:
    return time.strftime("%H:%M:%S", time.localtime(epoch)) + f".{int(epoch % 1 * 1000):03d}"


class ChangeLines:
    """One line per change for a human; remembers the names of the services it saw (from the
    state read first, then from the changes), so that a removed service is named too."""

    def __init__(self) -> None:
        #: (robot id, or None for this robot) -> service id -> name
        self.names: dict[str | None, dict[str, str]] = {}

    def learn(self, robot_id: str | None, services: Iterable[Mapping[str, Any]]) -> None:
        known = self.names.setdefault(robot_id, {})
        for s in services:
            if isinstance(s, Mapping) and "id" in s:
                known[str(s["id"])] = str(s.get("name"))

    def learn_robots(self, robots: Iterable[Mapping[str, Any]]) -> None:
        """The robots of /neighbors or /history."""
        for r in robots:
            self.learn(r.get("robot_id"), r.get("services") or [])

    def _named(self, robot_id: str | None, sid: object) -> str:
        name = self.names.get(robot_id, {}).get(str(sid))
        return f"{sid}" if name is None else f"{name} ({sid})"

    def line(self, change: Change) -> str:
        """When, what, which robot, the details that matter."""
        d = change.data
        rid = change.robot_id
        who = rid or "this robot"
        kind = change.event
        if kind == "robot.appeared":
            self.learn(rid, d.get("services") or [])
            listed = names(d.get("services") or [])
            what = f"appeared at {d.get('address') or '-'}" + ("" if d.get("new") else " again")
            if d.get("services_truncated"):
                listed = f"{d.get('services_count')} services"
            text = f"+ {who} {what} ({listed})"
        elif kind in ("robot.left", "robot.unreachable"):
            how = "left (said goodbye)" if kind == "robot.left" else "became unreachable"
            reason = f", {d['reason']}" if d.get("reason") else ""
            text = f"- {who} {how}{reason}"
        elif kind == "robot.services":
            added, changed = d.get("added") or [], d.get("changed") or []
            parts = [f"-{self._named(rid, sid)}" for sid in d.get("removed") or []]
            self.learn(rid, [*added, *changed])
            parts = [f"+{s.get('name')} ({s.get('id')})" for s in added] + parts
            parts += [f"~{s.get('name')} ({s.get('id')})" for s in changed]
            text = f"~ {who} services: {', '.join(parts) or 'changed'}"
        elif kind == "robot.address":
            text = f"~ {who} moved from {d.get('previous')} to {d.get('address')}"
        elif kind == "robot.indicator":
            arrow = "rose above" if d.get("direction") == "up" else "fell below"
            value = _indicator(d.get("indicator"))
            text = f"! {who} indicator {value} {arrow} {d.get('threshold')}"
        elif kind == "robot.forgotten":
            text = f"- {who} forgotten (the history map was full)"
        elif kind.startswith("service."):
            service = d.get("service") or {}
            if service:
                self.learn(None, [service])
            verb = kind.split(".")[1]
            lease = f", lease {d['ttl']:g} s" if d.get("ttl") else ""
            text = f"* {verb} {self._named(None, d.get('service_id'))}{lease}"
        elif kind == "resync":
            text = "! some changes are no longer kept: read the state again (sdfr neighbors)"
        else:
            text = f"? {kind} {who}"
        return f"{_clock(change.time)}  {text}"


def describe_change(change: Change) -> str:
    """One change's line, knowing no names but those the change carries."""
    return ChangeLines().line(change)
