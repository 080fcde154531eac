"""`netlab status`: what is left of each lab, from its manifest and the kernel, as a table.

`lab_status` gathers (it reads /proc and the namespaces); `format_status` only formats, so
that the table is tested without a lab.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from netlab import cleanup, kernel, manifest, naming
from netlab.errors import NetlabError
from netlab.manifest import Manifest, ProcRecord
from netlab.ranges import Topology

UNITS = {"delay": "ms", "jitter": "ms", "rate": "bit/s"}


def _proc_alive(rec: ProcRecord) -> bool:
    return cleanup.running(rec.pid) and cleanup.start_time(rec.pid) == rec.start


def shape_text(params: Mapping[str, Any]) -> str:
    """A link shape's non-zero parameters: ``loss 10%, delay 20ms``."""
    return ", ".join(f"{k} {v:g}{UNITS.get(k, '%')}" for k, v in params.items() if v)


def medium_state(record: Manifest) -> dict[str, Any] | None:
    """The medium in effect (partition, pair and link loss, who hears whom), as recorded by
    `netlab up`/`partition`/`merge`/`shape`; None when its runner keeps it (a scenario run)."""
    if not record.medium:
        return None
    try:
        topology = Topology.from_json(record.medium)
    except (KeyError, TypeError, ValueError, NetlabError) as exc:
        return {"error": f"unreadable medium record: {exc}"}
    links = topology.links()
    shapes = {r: shape_text(p) for r, p in record.medium.get("shapes", {}).items()}
    return {
        "model": record.medium.get("model", {}),
        "groups": None if topology.groups is None else [sorted(g) for g in topology.groups],
        "pair_loss": [[a, b, loss] for (a, b), loss in sorted(topology.pair_loss.items())],
        "shapes": {r: s for r, s in shapes.items() if s},
        "hears": {r: sorted(a for (a, b) in links if b == r) for r in record.robots},
        "links": len(links),
    }


def lab_status(record: Manifest) -> dict[str, Any]:
    """What is left of a lab, from its manifest and the kernel."""
    present = set(kernel.list_ns(naming.prefix(record.name)))
    daemons: dict[str, int] = {}
    for rec in record.processes:
        if rec.role == "sdfrd" and _proc_alive(rec):
            daemons[rec.robot] = rec.pid
    runner_alive = (
        cleanup.running(record.runner_pid)
        and cleanup.start_time(record.runner_pid) == record.runner_start
    )
    return {
        "name": record.name,
        "runner": {"pid": record.runner_pid, "alive": runner_alive, "detached": record.detached},
        "workdir": record.workdir,
        "medium": naming.air_ns(record.name) in present,
        "medium_state": medium_state(record),
        "robots": {
            name: {
                "runtime": r.runtime,
                "namespace": r.ns,
                "present": r.ns in present,
                "address": r.address,
                "mac": r.mac,
                "sdfrd": daemons.get(name),
            }
            for name, r in record.robots.items()
        },
        "processes": sum(1 for p in record.processes if _proc_alive(p)),
    }


def orphans() -> dict[str, list[str]]:
    """Namespaces named like a lab's whose lab has no manifest: lab name -> namespaces."""
    known = set(manifest.names())
    out: dict[str, list[str]] = {}
    for ns in kernel.list_ns(naming.NS_PREFIX):
        lab = ns[len(naming.NS_PREFIX) :].split("-", 1)[0]
        if naming.LAB_NAME_RE.match(lab) and lab not in known and "-" in ns[3:]:
            out.setdefault(lab, []).append(ns)
    return out


def _table(rows: Sequence[Sequence[str]]) -> list[str]:
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    return ["  " + "  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip()
            for row in rows]  # fmt: skip


def _medium_lines(lab: Mapping[str, Any]) -> list[str]:
    state = lab["medium_state"]
    if not lab["medium"]:
        return ["medium: its namespace is MISSING (`netlab down " + lab["name"] + "`)"]
    if state is None:
        return [f"medium: kept by its runner (pid {lab['runner']['pid']}), not recorded here"]
    if "error" in state:
        return [f"medium: {state['error']}"]
    model = state["model"]
    n = len(lab["robots"])
    reach = f"range {model.get('radius', '?'):g} m" if "radius" in model else "range ?"
    if state["groups"] is None:
        part = "no partition"
    else:
        named = {r for g in state["groups"] for r in g}
        rest = [r for r in lab["robots"] if r not in named]
        groups = [",".join(g) for g in state["groups"]] + ([",".join(rest)] if rest else [])
        part = "partition " + " | ".join(groups)
    lines = [f"medium: {part}; {reach}; {state['links']} of {n * (n - 1)} directed links up"]
    for a, b, loss in state["pair_loss"]:
        lines.append(f"  pair {a}->{b}: loss {loss:g}%")
    return lines


def format_status(labs: Sequence[Mapping[str, Any]], stray: Mapping[str, list[str]]) -> str:
    """`netlab status`'s text: a heading per lab, its medium, then a table of its robots."""
    lines: list[str] = []
    if not labs and not stray:
        lines.append("no labs (`netlab up NAME --robots N` makes one)")
    for lab in labs:
        runner = lab["runner"]
        if runner["alive"]:
            who = f"run by pid {runner['pid']}"
        elif runner["detached"]:
            who = "left up (netlab up)"  # its runner's exit is how `up` ends: no failure
        else:
            who = f"its runner (pid {runner['pid']}) DIED: `netlab down {lab['name']}`"
        robots = lab["robots"]
        lines.append(f"lab {lab['name']}: {len(robots)} robots, {who}")
        lines.append(f"folder: {lab['workdir']} (daemon logs: `netlab logs {lab['name']} ROBOT`)")
        lines += _medium_lines(lab)
        state = lab["medium_state"] or {}
        hears, shapes = state.get("hears"), state.get("shapes", {})
        rows = [["ROBOT", "ADDRESS", "MAC", "KIND", "NETNS", "SDFRD", "HEARS", "SHAPE"]]
        for name, r in robots.items():
            rows.append([
                name,
                r["address"],
                r["mac"],
                "container" if r["runtime"] == "docker" else "namespace",
                "ok" if r["present"] else "MISSING",
                f"pid {r['sdfrd']}" if r["sdfrd"] else "stopped",
                "?" if hears is None else str(len(hears.get(name, []))),
                shapes.get(name, "-"),
            ])  # fmt: skip
        lines += _table(rows)
    for lab_name, nss in sorted(stray.items()):
        lines.append(
            f"left behind (no manifest): {', '.join(nss)}; `netlab down {lab_name}` removes them"
        )
    return "\n".join(lines)
