"""A lab laid out as a scenario file describes it: its robots (names, kinds, positions, twin
MACs for collisions), and for ``netlab up -t FILE`` the medium steps of the file, applied at
once in order (partition, merge, move, quality, shape: a topology file is a scenario file
whose steps only lay out the medium)."""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from typing import Any

from netlab.errors import NetlabError
from netlab.scenario.backend import LabLike
from netlab.scenario.model import Scenario, step_ref
from netlab.scenario.spec import ScenarioError, pairs_of, select_groups
from netlab.scenario.steps import Merge, Move, Partition, Quality, Shape, twin_mac

#: The steps a topology file may have.
LAYOUT_STEPS = (Partition, Merge, Move, Quality, Shape)


def for_up(args: argparse.Namespace) -> Scenario:
    """The lab `netlab up` makes, as a scenario with no timeline: `args.topology`'s file (or
    `args.robots` robots), `args`' flags overriding it; NetlabError naming a file's mistake."""
    from netlab.scenario.files import find, load

    flags = {
        key: getattr(args, key)
        for key in ("seed", "fleet", "radius", "spacing", "runtime", "medium")
        if getattr(args, key, None) is not None
    }
    try:
        if args.topology is None:
            return Scenario("up", robots=args.robots, **{"spacing": 0.0, **flags})
        sc = load(find(args.topology))
        check_layout(sc)
        return replace(sc, **flags)
    except ScenarioError as exc:
        raise NetlabError(str(exc)) from None


def start_for_up(lab: LabLike, sc: Scenario, beacon_interval: float | None, from_file: bool) -> str:
    """`netlab up --start`: sdfrd on every robot, with the scenario's options and the beacon
    given, else the file's (`from_file`), else sdfrd's own; what it took, said."""
    t0 = time.monotonic()
    opts: dict[str, Any] = dict(sc.sdfrd)
    beacon = beacon_interval or (sc.beacon if from_file else None)
    if beacon is not None:
        opts["beacon_interval"] = beacon
    n = len(sc.names)
    lab.start_all(timeout=max(60.0, 2.0 * n), **opts)
    return f"sdfrd runs on all {n} robots, healthy in {time.monotonic() - t0:.2f} s"


def add_robots(lab: LabLike, sc: Scenario) -> None:
    """The scenario's robots, where it puts them, of the kinds it says; the first robot of a
    collision gets its own MAC, each other one a twin of it.  The medium is loaded once."""
    positions = sc.initial_positions()
    together = {r: group for group in sc.collisions() for r in group}
    add_all = getattr(lab, "add_robot_batch", None)  # (a lab across hosts: a request a host)
    if add_all is not None and not together:  # (a twin needs its first's MAC)
        add_all([(name, positions[name], None, sc.runtime_of(name)) for name in sc.names])
        return
    added: set[str] = set()
    with lab.batch():
        for name in sc.names:
            group = together.get(name, ())
            first = next((r for r in group if r in added), None)
            mac = twin_mac(lab.robot(first).mac, group.index(name)) if first is not None else None
            lab.add_robot(name, pos=positions[name], mac=mac, runtime=sc.runtime_of(name))
            added.add(name)


def check_layout(sc: Scenario) -> None:
    """ScenarioError unless every step of `sc` lays out the medium."""
    for i, step in enumerate(sc.steps, 1):
        if not isinstance(step, LAYOUT_STEPS):
            kinds = ", ".join(cls.kind for cls in LAYOUT_STEPS)
            raise ScenarioError(
                f"{sc.source or sc.name}: {step_ref(i, step)}: a topology's steps lay out the "
                f"medium ({kinds}); use `netlab run` for a timeline"
            )


def lay_out(lab: LabLike, sc: Scenario) -> list[str]:
    """Apply the scenario's steps (all of LAYOUT_STEPS, see `check_layout`) to the lab's
    medium in order, as one change; what each did."""
    check_layout(sc)
    ctx = sc.selectors()
    done: list[str] = []
    with lab.batch():
        for step in sc.steps:
            if isinstance(step, Partition):
                groups = select_groups(ctx, step.groups)
                lab.partition(groups)
                done.append("partition " + " | ".join(",".join(g) for g in groups))
            elif isinstance(step, Merge):
                lab.merge()
                done.append("merge")
            elif isinstance(step, Move):
                lab.move(step.robot, (float(step.to[0]), float(step.to[1])))
                done.append(f"move {step.robot} to ({step.to[0]:g}, {step.to[1]:g})")
            elif isinstance(step, Quality):
                names = ctx.robots(step.robots)
                peers = ctx.robots(step.peers) if step.peers is not None else names
                pairs = pairs_of(names, peers, both=step.both)
                for a, b in pairs:
                    lab.set_pair_quality(a, b, loss=step.loss, both=step.both)
                loss = "the range model" if step.loss is None else f"{step.loss:g} % loss"
                done.append(f"quality: {loss} on {len(pairs)} pair{'s' * (len(pairs) != 1)}")
            elif isinstance(step, Shape):
                for name in ctx.robots(step.robots):
                    lab.shape(name, **dict(step.params))
                params = ", ".join(f"{k} {v}" for k, v in step.params.items()) or "no shaping"
                done.append(f"shape {','.join(ctx.robots(step.robots))}: {params}")
    return done
