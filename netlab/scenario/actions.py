"""What each action step does to a lab: one function per step kind, registered with `acts`.

Each takes the run (`netlab.scenario.engine.Run`: the lab, the scenario, who runs, what
was published, the truth log) and its step, and returns the progress line to print.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

from netlab.judging import fmt_set
from netlab.mobility import RandomWaypoint, walk
from netlab.ranges import Pos
from netlab.scenario.spec import StepError, pairs_of, select_groups
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

if TYPE_CHECKING:
    from netlab.scenario.engine import Run

S = TypeVar("S", bound=Step)
Action = Callable[["Run", Any], str]

#: Step class -> what carries it out.
ACTIONS: dict[type[Step], Action] = {}


def acts(cls: type[S]) -> Callable[[Callable[[Run, S], str]], Callable[[Run, S], str]]:
    def register(fn: Callable[[Run, S], str]) -> Callable[[Run, S], str]:
        ACTIONS[cls] = fn
        return fn

    return register


@acts(Start)
def start(run: Run, step: Start) -> str:
    names = run.names(step.robots)
    t = run.clock.monotonic()
    run.lab.start_all(names, timeout=max(60.0, 2.0 * len(names)), **run.options(step))
    run.running += [n for n in names if n not in run.running]
    run.record_truth()
    took = run.clock.monotonic() - t
    return f"start {run.text(names)}: sdfrd healthy on {len(names)} in {took:.2f} s"


@acts(Stop)
def stop(run: Run, step: Stop) -> str:
    names = run.names(step.robots)
    for n in names:
        run.lab.stop(n)
        run.gone(n)
    return f"stop {run.text(names)} (SIGTERM: Byebye)"


@acts(Kill)
def kill(run: Run, step: Kill) -> str:
    names = run.names(step.robots)
    for n in names:
        run.lab.kill(n)
        run.gone(n)
    return f"kill -9 {run.text(names)} (silent)"


@acts(Restart)
def restart(run: Run, step: Restart) -> str:
    names = run.names(step.robots)
    for n in names:
        if step.hard:
            if n in run.running:
                run.lab.kill(n)
                run.gone(n)
            run.lab.start(n, **run.options())
        else:
            run.lab.restart(n, **run.options())
        if n not in run.running:
            run.running.append(n)
        run.record_truth()
    return f"restart {run.text(names)} ({'kill -9' if step.hard else 'SIGTERM'}, start)"


@acts(Partition)
def partition(run: Run, step: Partition) -> str:
    groups = select_groups(run.ctx, step.groups)
    run.lab.partition(groups)
    run.record_truth()
    rest = [n for n in run.sc.names if not any(n in g for g in groups)]
    return "partition " + " | ".join(fmt_set(g) for g in [*groups, *([rest] if rest else [])])


@acts(Merge)
def merge(run: Run, step: Merge) -> str:
    run.lab.merge()
    run.record_truth()
    return "merge: the partition ends"


@acts(Move)
def move(run: Run, step: Move) -> str:
    run.lab.move(step.robot, (float(step.to[0]), float(step.to[1])))
    hears = {a for (a, b) in run.record_truth().links if b == step.robot}
    return f"move {step.robot} to ({step.to[0]:g}, {step.to[1]:g}): in range of {fmt_set(hears)}"


@acts(Mobility)
def mobility(run: Run, step: Mobility) -> str:
    names = run.names(step.robots)
    duration = run.seconds(step.quick if run.quick and step.quick is not None else step.duration)
    area = step.area or run.sc.area
    here = run.lab.positions()
    model = RandomWaypoint(
        names,
        area=area,
        speed=step.speed,
        pause=step.pause,
        seed=run.sc.seed if step.seed is None else step.seed,
        start={n: here[n] for n in names},
    )
    run.say(
        f"mobility: random waypoint for {len(names)} robots in {area[0]:g} x {area[1]:g} m "
        f"at {step.speed[0]:g}-{step.speed[1]:g} m/s, {duration:g} s"
    )
    report_every = max(10.0, duration / 6)
    linked: list[int] = []
    progress = {"changes": 0, "next": report_every}
    last = [run.truth.now()]

    def apply(t: float, positions: dict[str, Pos]) -> None:
        with run.lab.batch():
            for name, pos in positions.items():
                run.lab.move(name, pos)
        state = run.record_truth()
        progress["changes"] += len({frozenset(p) for p in state.links ^ last[0].links})
        linked.append(state.linked_pairs())
        last[0] = state
        done = t + step.tick
        if progress["next"] <= done <= duration:
            run.say(
                f"mobility: {done:.0f} of {duration:g} s, {linked[-1]} pairs "
                f"linked, {progress['changes']} link changes so far"
            )
            progress["next"] += report_every

    walk(model, duration, step.tick, apply, clock=run.clock.monotonic, sleep=run.clock.sleep)
    pairs = len(names) * (len(names) - 1) // 2
    mean = sum(linked) / len(linked) if linked else 0.0
    return (
        f"mobility done: {progress['changes']} link changes in {duration:g} s, "
        f"{mean:.1f} of {pairs} pairs linked on average"
    )


@acts(Quality)
def quality(run: Run, step: Quality) -> str:
    names = run.names(step.robots)
    peers = run.names(step.peers) if step.peers is not None else names
    pairs = pairs_of(names, peers, both=step.both)
    with run.lab.batch():
        for a, b in pairs:
            run.lab.set_pair_quality(a, b, loss=step.loss, both=step.both)
    run.record_truth()
    what = "back to the range model" if step.loss is None else f"{step.loss:g} % loss"
    ways = "both ways" if step.both else "one way"
    return f"quality: {what} on {len(pairs)} pair{'s' if len(pairs) > 1 else ''} ({ways})"


@acts(Shape)
def shape(run: Run, step: Shape) -> str:
    names = run.names(step.robots)
    for n in names:
        run.lab.shape(n, **dict(step.params))
    run.record_truth()
    params = ", ".join(f"{k} {v}" for k, v in step.params.items()) or "no shaping"
    return f"shape {run.text(names)}: {params}"


@acts(Publish)
def publish(run: Run, step: Publish) -> str:
    names = run.names(step.robots)
    for n in names:
        run.need_running(n, "publish")
        if step.service in run.services[n]:
            raise StepError(f"{n} already has a service {step.service!r} from this run")
        client = run.probe.client(n)
        sid = client.publish(step.service, step.type, step.url, dict(step.attributes))
        run.services[n][step.service] = sid
    return f"publish {step.service!r} ({step.type}) on {run.text(names)}"


@acts(Unpublish)
def unpublish(run: Run, step: Unpublish) -> str:
    names = run.names(step.robots)
    for n in names:
        run.need_running(n, "unpublish")
        known = run.services[n].get(step.service)
        if known is None:
            raise StepError(f"{n} has no service {step.service!r} published by this run")
        run.probe.client(n).unpublish(known)
        del run.services[n][step.service]
    return f"unpublish {step.service!r} on {run.text(names)}"


@acts(Collision)
def collision(run: Run, step: Collision) -> str:
    # The MACs were given when the lab was made (`Run.add_robots`); this says so in order.
    macs = ", ".join(f"{r} {run.lab.robot(r).mac}" for r in step.robots)
    auto = run.sc.addressing == "auto"
    note = "" if auto else "; it matters only with addressing = auto, not set here"
    return f"collision: MACs ending alike, one derived address: {macs} (at lab creation{note})"


@acts(Sleep)
def sleep(run: Run, step: Sleep) -> str:
    wait = run.seconds(step.quick if run.quick and step.quick is not None else step.duration)
    run.clock.sleep(wait)
    return f"slept {wait:g} s"
