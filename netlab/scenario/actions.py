"""What each action step does to a lab: one function per step kind, registered with `acts`.

Each takes a `netlab.scenario.context.StepContext` (the lab, the clock, the fleet: who runs
and what this run published, the probe, the truth log) and its step, and returns the
progress line to print.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

from netlab.judging import fmt_set
from netlab.mobility import RandomWaypoint, walk
from netlab.ranges import Pos
from netlab.scenario.context import StepContext
from netlab.scenario.spec import Robots, StepError, pairs_of
from netlab.scenario.steps import (
    Collision,
    Kill,
    Merge,
    Mobility,
    Move,
    Partition,
    Publish,
    Quality,
    Restart,
    Shape,
    Sleep,
    Start,
    Step,
    Stop,
    Unpublish,
)

S = TypeVar("S", bound=Step)
Action = Callable[[StepContext, Any], str]

#: Step class -> what carries it out.
ACTIONS: dict[type[Step], Action] = {}


def acts(
    cls: type[S],
) -> Callable[[Callable[[StepContext, S], str]], Callable[[StepContext, S], str]]:
    def register(fn: Callable[[StepContext, S], str]) -> Callable[[StepContext, S], str]:
        ACTIONS[cls] = fn
        return fn

    return register


@acts(Start)
def start(ctx: StepContext, step: Start) -> str:
    names = ctx.fleet.names(step.robots)
    t = ctx.clock.monotonic()
    limit = max(60.0, 2.0 * len(names)) if step.within is None else ctx.seconds(step.within)
    ctx.lab.start_all(names, timeout=limit, **ctx.options(step))
    ctx.fleet.started(names)
    took = ctx.clock.monotonic() - t
    return f"start {ctx.text(names)}: sdfrd healthy on {len(names)} in {took:.2f} s"


def _end(ctx: StepContext, sel: Robots, end: Callable[[str], object]) -> tuple[str, ...]:
    """End the daemons of the robots `sel` names with `end`, one after the other."""
    names = ctx.fleet.names(sel)
    for n in names:
        end(n)
        ctx.fleet.gone(n)
    return names


@acts(Stop)
def stop(ctx: StepContext, step: Stop) -> str:
    names = _end(ctx, step.robots, ctx.lab.stop)
    return f"stop {ctx.text(names)} (SIGTERM: Byebye)"


@acts(Kill)
def kill(ctx: StepContext, step: Kill) -> str:
    names = _end(ctx, step.robots, ctx.lab.kill)
    return f"kill -9 {ctx.text(names)} (silent)"


@acts(Restart)
def restart(ctx: StepContext, step: Restart) -> str:
    names = ctx.fleet.names(step.robots)
    for n in names:
        if step.hard:
            if ctx.fleet.runs(n):
                ctx.lab.kill(n)
                ctx.fleet.gone(n)
            ctx.lab.start(n, **ctx.options())
        else:
            ctx.lab.restart(n, **ctx.options())
        ctx.fleet.started([n])
    return f"restart {ctx.text(names)} ({'kill -9' if step.hard else 'SIGTERM'}, start)"


@acts(Partition)
def partition(ctx: StepContext, step: Partition) -> str:
    groups = ctx.fleet.groups(step.groups)
    ctx.lab.partition(groups)
    ctx.fleet.record_truth()
    rest = [n for n in ctx.scenario.names if not any(n in g for g in groups)]
    return "partition " + " | ".join(fmt_set(g) for g in [*groups, *([rest] if rest else [])])


@acts(Merge)
def merge(ctx: StepContext, step: Merge) -> str:
    ctx.lab.merge()
    ctx.fleet.record_truth()
    return "merge: the partition ends"


@acts(Move)
def move(ctx: StepContext, step: Move) -> str:
    ctx.lab.move(step.robot, (float(step.to[0]), float(step.to[1])))
    hears = {a for (a, b) in ctx.fleet.record_truth().links if b == step.robot}
    return f"move {step.robot} to ({step.to[0]:g}, {step.to[1]:g}): in range of {fmt_set(hears)}"


@acts(Mobility)
def mobility(ctx: StepContext, step: Mobility) -> str:
    names = ctx.fleet.names(step.robots)
    duration = ctx.duration(step.duration, step.quick)
    area = step.area or ctx.scenario.area
    here = ctx.lab.positions()
    model = RandomWaypoint(
        names,
        area=area,
        speed=step.speed,
        pause=step.pause,
        seed=ctx.scenario.seed if step.seed is None else step.seed,
        start={n: here[n] for n in names},
    )
    ctx.say(
        f"mobility: random waypoint for {len(names)} robots in {area[0]:g} x {area[1]:g} m "
        f"at {step.speed[0]:g}-{step.speed[1]:g} m/s, {duration:g} s"
    )
    report_every = max(10.0, duration / 6)
    linked: list[int] = []
    progress = {"changes": 0, "next": report_every}
    last = [ctx.truth.now()]

    def apply(t: float, positions: dict[str, Pos]) -> None:
        with ctx.lab.batch():
            for name, pos in positions.items():
                ctx.lab.move(name, pos)
        state = ctx.fleet.record_truth()
        progress["changes"] += len({frozenset(p) for p in state.links ^ last[0].links})
        linked.append(state.linked_pairs())
        last[0] = state
        done = t + step.tick
        if progress["next"] <= done <= duration:
            ctx.say(
                f"mobility: {done:.0f} of {duration:g} s, {linked[-1]} pairs "
                f"linked, {progress['changes']} link changes so far"
            )
            progress["next"] += report_every

    walk(model, duration, step.tick, apply, clock=ctx.clock.monotonic, sleep=ctx.clock.sleep)
    pairs = len(names) * (len(names) - 1) // 2
    mean = sum(linked) / len(linked) if linked else 0.0
    return (
        f"mobility done: {progress['changes']} link changes in {duration:g} s, "
        f"{mean:.1f} of {pairs} pairs linked on average"
    )


@acts(Quality)
def quality(ctx: StepContext, step: Quality) -> str:
    names = ctx.fleet.names(step.robots)
    peers = ctx.fleet.names(step.peers) if step.peers is not None else names
    pairs = pairs_of(names, peers, both=step.both)
    with ctx.lab.batch():
        for a, b in pairs:
            ctx.lab.set_pair_quality(a, b, loss=step.loss, both=step.both)
    ctx.fleet.record_truth()
    what = "back to the range model" if step.loss is None else f"{step.loss:g} % loss"
    ways = "both ways" if step.both else "one way"
    return f"quality: {what} on {len(pairs)} pair{'s' if len(pairs) > 1 else ''} ({ways})"


@acts(Shape)
def shape(ctx: StepContext, step: Shape) -> str:
    names = ctx.fleet.names(step.robots)
    for n in names:
        ctx.lab.shape(n, **dict(step.params))
    ctx.fleet.record_truth()
    params = ", ".join(f"{k} {v}" for k, v in step.params.items()) or "no shaping"
    return f"shape {ctx.text(names)}: {params}"


@acts(Publish)
def publish(ctx: StepContext, step: Publish) -> str:
    names = ctx.fleet.names(step.robots)
    for n in names:
        ctx.fleet.need_running(n, "publish")
        if step.service in ctx.fleet.services[n]:
            raise StepError(f"{n} already has a service {step.service!r} from this run")
        client = ctx.probe.client(n)
        sid = client.publish(step.service, step.type, step.url, dict(step.attributes))
        ctx.fleet.services[n][step.service] = sid
    return f"publish {step.service!r} ({step.type}) on {ctx.text(names)}"


@acts(Unpublish)
def unpublish(ctx: StepContext, step: Unpublish) -> str:
    names = ctx.fleet.names(step.robots)
    for n in names:
        ctx.fleet.need_running(n, "unpublish")
        known = ctx.fleet.services[n].get(step.service)
        if known is None:
            raise StepError(f"{n} has no service {step.service!r} published by this run")
        ctx.probe.client(n).unpublish(known)
        del ctx.fleet.services[n][step.service]
    return f"unpublish {step.service!r} on {ctx.text(names)}"


@acts(Collision)
def collision(ctx: StepContext, step: Collision) -> str:
    # The MACs were given when the lab was made (`topology.add_robots`); this says so in order.
    macs = ", ".join(f"{r} {ctx.lab.robot(r).mac}" for r in step.robots)
    auto = ctx.scenario.addressing == "auto"
    note = "" if auto else "; it matters only with addressing = auto, not set here"
    return f"collision: MACs ending alike, one derived address: {macs} (at lab creation{note})"


@acts(Sleep)
def sleep(ctx: StepContext, step: Sleep) -> str:
    wait = ctx.duration(step.duration, step.quick)
    ctx.clock.sleep(wait)
    return f"slept {wait:g} s"
