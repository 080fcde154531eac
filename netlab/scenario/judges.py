"""How each condition is judged: one function per condition kind, registered by class.

A *polled* condition has an evaluator (`@evaluates`): it looks at the fleet now and returns
what is wrong (nothing: it holds); the engine polls it up to the check's deadline.  Any other
condition has a judge (`@judges`), called once with the check's result to fill in: over the
samples and /proc readings the run gathered, or (updates) left for the captures at the end.
The pure comparisons live in `netlab.judging` and `netlab.samples`; these functions gather
their inputs.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

from netlab import procstat
from netlab.analysis import natural_order
from netlab.judging import (
    address_problems,
    expect_problems,
    fmt_set,
    history_problems,
    indicator_problems,
    unreachable_problems,
)
from netlab.samples import agreement, flaps
from netlab.scenario.backend import LabLike
from netlab.scenario.conditions import (
    Agreement,
    Condition,
    DistinctAddresses,
    Flaps,
    Indicator,
    InHistory,
    Lists,
    Medium,
    Resources,
    Unreachable,
    Updates,
)
from netlab.scenario.context import CheckContext
from netlab.scenario.model import reference
from netlab.scenario.results import CheckResult

C = TypeVar("C", bound=Condition)
Evaluator = Callable[[CheckContext, Any], list[str]]
Judge = Callable[[CheckContext, int, Any, CheckResult], None]

#: Polled condition class -> what is wrong now (an empty list: it holds).
EVALUATORS: dict[type[Condition], Evaluator] = {}
#: Polled condition class -> what it adds to its result once it held (or not).
AFTER_POLL: dict[type[Condition], Callable[[CheckContext, Any, CheckResult], None]] = {}
#: Judged-once condition class -> fills in the check's result.
JUDGES: dict[type[Condition], Judge] = {}


def evaluates(cls: type[C]) -> Callable[[Callable[[CheckContext, C], list[str]]], Any]:
    def register(
        fn: Callable[[CheckContext, C], list[str]],
    ) -> Callable[[CheckContext, C], list[str]]:
        EVALUATORS[cls] = fn
        return fn

    return register


def judges(cls: type[C]) -> Callable[[Callable[[CheckContext, int, C, CheckResult], None]], Any]:
    def register(
        fn: Callable[[CheckContext, int, C, CheckResult], None],
    ) -> Callable[[CheckContext, int, C, CheckResult], None]:
        JUDGES[cls] = fn
        return fn

    return register


def say_verdict(ctx: CheckContext, res: CheckResult) -> None:
    ctx.say(f"{'ok   ' if res.ok else 'FAIL '} {res.description}: {res.detail}")


# ---------------------------------------------------------------------------------------------
# Polled


@evaluates(Lists)
def lists(ctx: CheckContext, cond: Lists) -> list[str]:
    running = set(ctx.fleet.running)
    if cond.groups is not None:
        groups = ctx.fleet.groups(cond.groups)
    else:
        groups = [ctx.fleet.names(cond.robots if cond.robots is not None else "running")]
    expected: dict[str, set[str]] = {}
    for g in groups:
        members = [r for r in g if r in running]
        if not members:
            return [f"no robot of {fmt_set(g)} runs"]
        expected.update({a: set(members) - {a} for a in members})
    views = ctx.probe.neighbours(expected)
    services = {r: set(s) for r, s in ctx.fleet.services.items()} if cond.services else None
    return expect_problems(views, expected, services=services, exact=cond.exact)


@evaluates(Medium)
def medium(ctx: CheckContext, cond: Medium) -> list[str]:
    state = ctx.truth.now()
    robots = ctx.fleet.running_of(cond.robots)
    expected = {a: state.expected(a) for a in robots}
    services = {r: set(s) for r, s in ctx.fleet.services.items()} if cond.services else None
    return expect_problems(ctx.probe.neighbours(robots), expected, services=services)


@evaluates(Unreachable)
def unreachable(ctx: CheckContext, cond: Unreachable) -> list[str]:
    gone = ctx.fleet.names(cond.robots)
    on = [r for r in ctx.fleet.running_of(cond.on) if r not in gone]
    return unreachable_problems(ctx.probe.neighbours(on), gone, on)


@evaluates(InHistory)
def in_history(ctx: CheckContext, cond: InHistory) -> list[str]:
    kept = ctx.fleet.names(cond.robots)
    on = [r for r in ctx.fleet.running_of(cond.on) if r not in kept]
    fell_from = (
        ctx.history.indicators_before_last_step(ctx.observer.samples) if cond.falling else None
    )
    return history_problems(
        ctx.probe.histories(on),
        kept,
        on,
        reachable=cond.reachable,
        indicator_below=cond.indicator_below,
        fell_from=fell_from,
    )


def round_trips(lab: LabLike) -> dict[tuple[str, str], float]:
    """(robot, peer) -> the share of robot's pings to peer the medium lets come back."""
    links = lab.links()  # (sender, receiver) -> loss in %
    return {
        (a, b): (1 - loss / 100.0) * (1 - links[(b, a)] / 100.0)
        for (a, b), loss in links.items()
        if (b, a) in links
    }


@evaluates(Indicator)
def indicator(ctx: CheckContext, cond: Indicator) -> list[str]:
    robots = ctx.fleet.running_of(cond.robots)
    return indicator_problems(ctx.probe.neighbours(robots), round_trips(ctx.lab), cond.tolerance)


def _indicator_data(ctx: CheckContext, cond: Indicator, res: CheckResult) -> None:
    rates = round_trips(ctx.lab)
    seen: dict[str, dict[str, float | None]] = {}
    errors: list[float] = []
    for robot, view in ctx.probe.neighbours(ctx.fleet.running_of(cond.robots)).items():
        seen[robot] = {}
        for peer in natural_order(list(view.reachable)):
            entry = view.entry(peer)
            ind = entry.indicator if entry is not None else None
            seen[robot][peer] = ind
            if ind is not None and (robot, peer) in rates:
                errors.append(abs(ind - rates[(robot, peer)]))
    values = sorted(rates.values())
    res.data = {
        "indicators": seen,
        "medium_round_trip": {"min": values[0], "max": values[-1]} if values else None,
        "abs_error": {"mean": sum(errors) / len(errors), "max": max(errors), "pairs": len(errors)}
        if errors
        else None,
    }
    if errors:
        note = (
            f"{len(errors)} pairs: |indicator - delivery| mean "
            f"{sum(errors) / len(errors):.3f}, max {max(errors):.3f}"
        )
        res.detail = f"{res.detail}; {note}" if res.detail else note
        ctx.say(f"      {note}")


AFTER_POLL[Indicator] = _indicator_data


@evaluates(DistinctAddresses)
def distinct_addresses(ctx: CheckContext, cond: DistinctAddresses) -> list[str]:
    robots = ctx.fleet.running_of(cond.robots)
    return address_problems(ctx.probe.neighbours(robots), ctx.probe.addresses(robots))


# ---------------------------------------------------------------------------------------------
# Judged once


@judges(Flaps)
def judge_flaps(ctx: CheckContext, index: int, cond: Flaps, res: CheckResult) -> None:
    ref, (start, end) = ctx.history.window(index, cond.over)
    per = ctx.seconds(cond.per)
    stats = flaps(ctx.observer.samples, ctx.truth.states(), per=per, start=start, end=end)
    res.at = ctx.elapsed()
    res.data = {"flaps": stats.to_json(), "over_step": ref}
    minutes = (end - start) / 60.0
    res.detail = (
        f"{stats.flaps} flaps among {stats.pairs} linked pairs in {minutes:.1f} min "
        f"({stats.samples} samples every {ctx.scenario.sample:g} s); at most {stats.most} of one "
        f"pair within {per:g} s (allowed {cond.at_most})"
    )
    if stats.samples < 2:
        res.ok = False
        res.detail = f"fewer than 2 samples in the window of step {ref}: cannot tell"
    else:
        res.ok = stats.most <= cond.at_most
        if not res.ok:
            worst = ", ".join(
                f"{a} dropped {b} {n} times (at "
                + ", ".join(f"{t - start:.1f}" for t in stats.at[a][b][:5])
                + " s)"
                for a, b, n in stats.worst[:3]
            )
            res.detail += f"; worst: {worst}"
    say_verdict(ctx, res)


@judges(Resources)
def judge_resources(ctx: CheckContext, index: int, cond: Resources, res: CheckResult) -> None:
    ref = reference(ctx.scenario.steps, index, cond.over)
    res.at = ctx.elapsed()
    before, after = ctx.history.usage.get(ref, ({}, {}))
    per = {
        r: procstat.window(before[r], after[r])
        for r in natural_order(list(before))
        if r in after and after[r].processes
    }
    if not per:
        res.detail = "no /proc readings of the daemons (lab without pids): not judged"
        ctx.say(f"skip  {res.description}: {res.detail}")
        return
    cpu = [u["cpu_percent"] for u in per.values()]
    pss = [u["pss_mib"] for u in per.values()]
    rss = [u["rss_mib"] for u in per.values()]
    wall = max(u["wall_s"] for u in per.values())
    res.data = {
        "over_step": ref,
        "daemons": len(per),
        "cpu_percent": {"mean": sum(cpu) / len(cpu), "max": max(cpu), "total": sum(cpu)},
        "pss_mib": {"mean": sum(pss) / len(pss), "max": max(pss), "total": sum(pss)},
        "rss_mib": {"mean": sum(rss) / len(rss), "max": max(rss)},
        "per_daemon": per,
    }
    res.detail = (
        f"{len(per)} daemons over {wall:.0f} s: CPU {sum(cpu) / len(cpu):.2f} % of one core "
        f"on average (max {max(cpu):.2f} %, all {sum(cpu):.0f} %); PSS "
        f"{sum(pss) / len(pss):.1f} MiB on average (max {max(pss):.1f}, all "
        f"{sum(pss):.0f} MiB), RSS {sum(rss) / len(rss):.1f} MiB"
    )
    over = []
    if cond.cpu_at_most is not None:
        over += [
            f"{r} used {u['cpu_percent']:.1f} % CPU"
            for r, u in per.items()
            if u["cpu_percent"] > cond.cpu_at_most
        ]
    if cond.pss_at_most is not None:
        over += [
            f"{r} took {u['pss_mib']:.1f} MiB"
            for r, u in per.items()
            if u["pss_mib"] > cond.pss_at_most
        ]
    res.ok = not over
    if over:
        res.detail += "; over the limit: " + ", ".join(over[:6])
    say_verdict(ctx, res)


@judges(Agreement)
def judge_agreement(ctx: CheckContext, index: int, cond: Agreement, res: CheckResult) -> None:
    ref, (start, end) = ctx.history.window(index, cond.over)
    lag = ctx.seconds(cond.lag)
    loss_lag = ctx.seconds(cond.loss_lag) if cond.loss_lag is not None else lag
    stats = agreement(
        ctx.observer.samples,
        ctx.truth.states(),
        lag=lag,
        loss_lag=loss_lag,
        start=start,
        end=end,
    )
    value = stats.pair_share if cond.measure == "pairs" else stats.sample_share
    res.at = ctx.elapsed()
    res.data = {
        "agreement": stats.to_json(),
        "lag_s": lag,
        "loss_lag_s": loss_lag,
        "over_step": ref,
    }
    other = stats.sample_share if cond.measure == "pairs" else stats.pair_share
    other_name = "samples fully agreeing" if cond.measure == "pairs" else "pairs agreeing"
    lags = f"lag {lag:g} s" + (f", {loss_lag:g} s for lost links" if loss_lag != lag else "")
    res.detail = (
        f"{value:.1%} of {cond.measure} agree over {stats.samples} samples of step {ref} "
        f"(target {cond.at_least:.0%}, {lags}; {other:.1%} {other_name}; wrong: "
        f"{stats.stale} stale, {stats.missing} missing)"
    )
    if stats.samples == 0:
        res.ok = False
        res.detail = (
            f"no samples in the window of step {ref} (observer every {ctx.scenario.sample} s)"
        )
    else:
        res.ok = value >= cond.at_least
        if not res.ok and stats.worst:
            worst = ", ".join(
                f"{a} on {b} wrong in {share:.0%} of samples" for a, b, share in stats.worst[:3]
            )
            res.detail += f"; worst: {worst}"
    say_verdict(ctx, res)


@judges(Updates)
def judge_updates(ctx: CheckContext, index: int, cond: Updates, res: CheckResult) -> None:
    _, (since, _) = ctx.history.window(index, cond.after)
    res.at = ctx.elapsed()
    if not ctx.captured:
        res.detail = "needs captures (capture is 'none'): not judged"
        ctx.say(f"skip  {res.description}: {res.detail}")
        return
    ctx.history.deferred.append((res, cond, since, ctx.clock.time()))
    ctx.say(f"...   {res.description}: counted in the captures at the end")
