"""The scenario engine's seams: its registries are complete, and its time is injected, so a
whole scenario at the product's 10 s beacon with two minutes of mobility runs against a fake
lab in virtual time, in an instant, with deadlines counted in that time."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from netlab.clock import VirtualClock
from netlab.observe import Probe
from netlab.ranges import UnitDisc
from netlab.scenario import (
    CONDITIONS,
    PRODUCT_BEACON,
    STEPS,
    Agreement,
    Backend,
    Check,
    Condition,
    Flaps,
    Lists,
    Merge,
    Mobility,
    Partition,
    Publish,
    Scenario,
    Sleep,
    Start,
    Step,
    Stop,
    Unreachable,
    Wait,
    conditions,
    run,
    steps,
)
from netlab.scenario.actions import ACTIONS
from netlab.scenario.backend import LabSpec
from netlab.scenario.context import Fleet, StepContext
from netlab.scenario.judges import EVALUATORS, JUDGES
from netlab.truth import TruthLog
from tests.support.fakelab import FakeClient, FakeLab, quiet


def test_every_step_and_condition_class_is_registered() -> None:
    def defined(module: object, base: type) -> set[type]:
        found = {v for v in vars(module).values() if isinstance(v, type) and issubclass(v, base)}
        return found - {base}

    assert defined(steps, Step) == set(STEPS.values()), "a step class not added to STEPS"
    assert defined(conditions, Condition) == set(CONDITIONS.values()), "not in CONDITIONS"


def test_every_step_kind_has_one_action_and_every_condition_one_way_to_be_judged() -> None:
    actions = {cls for cls in STEPS.values() if not issubclass(cls, Check)}
    assert set(ACTIONS) == actions, "a step kind without its function in actions.py"
    polled = {cls for cls in CONDITIONS.values() if cls.polled}
    assert set(EVALUATORS) == polled, "a polled condition without its evaluator in judges.py"
    assert set(JUDGES) == set(CONDITIONS.values()) - polled, "a judged-once condition unjudged"


def test_an_action_needs_only_its_context_not_an_engine() -> None:
    sc = Scenario("alone", robots=3, groups={"pair": ["r1", "r2"]}, capture="none")
    lab = FakeLab(LabSpec("alone", 0, 1, UnitDisc(50.0))).up()
    for i, name in enumerate(sc.names):
        lab.add_robot(name, pos=(float(i), 0.0))
    clock, truth = VirtualClock(), TruthLog()
    fleet = Fleet(sc.selectors(), lab, truth)
    probe = Probe(lambda r: FakeClient(lab, r))
    ctx = StepContext(sc, lab, clock, fleet, probe, truth, quiet([]))
    said = ACTIONS[Start](ctx, Start())
    assert said.startswith("start all 3: sdfrd healthy on 3")
    assert fleet.running == ("r1", "r2", "r3") and lab.running == {"r1", "r2", "r3"}
    assert ACTIONS[Stop](ctx, Stop("pair")) == "stop r1, r2 (SIGTERM: Byebye)"
    assert list(fleet.running) == ["r3"] and fleet.names("running") == ("r3",)
    assert truth.now().running == {"r3"}


def test_a_virtual_clock_fires_timers_in_order_while_time_is_slept_through() -> None:
    clock = VirtualClock(epoch=1000.0)
    seen: list[tuple[str, float]] = []
    stop_a = clock.every(2.0, lambda: seen.append(("a", clock.monotonic())))
    clock.every(3.0, lambda: seen.append(("b", clock.monotonic())))
    clock.sleep(6.5)
    assert seen == [("a", 2.0), ("b", 3.0), ("a", 4.0), ("a", 6.0), ("b", 6.0)]
    assert clock.monotonic() == 6.5 and clock.time() == 1006.5
    stop_a()
    clock.sleep(3.0)
    assert seen[5:] == [("b", 9.0)]
    with pytest.raises(ValueError, match="period must be positive"):
        clock.every(0, lambda: None)


def _virtual(backend: Backend, monkeypatch: pytest.MonkeyPatch) -> VirtualClock:
    clock = VirtualClock()

    def no_real_sleep(seconds: float) -> None:
        raise AssertionError(f"the engine slept {seconds} s of real time")

    monkeypatch.setattr(time, "sleep", no_real_sleep)
    return clock


def test_a_whole_scenario_at_the_product_beacon_runs_in_virtual_time(
    fake: tuple[Backend, list[FakeLab]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    backend, labs = fake
    clock = _virtual(backend, monkeypatch)
    sc = Scenario(
        "virtual",
        robots=6,
        beacon=PRODUCT_BEACON,
        radius=20.0,
        groups={"a": ["r1", "r2", "r3"], "b": ["r4", "r5", "r6"]},
        sample=1.0,
        capture="none",
        steps=[
            Start(),
            Publish("all", "camera", "sensor.camera"),
            Wait(Lists(services=True), within="1 beacon"),
            Partition(["a", "b"], label="split"),
            Check(Lists(groups=["a", "b"]), within="3 beacons + 0.5 s"),
            Merge(label="merge"),
            Check(Lists(), within="1 beacon + 1 s"),
            Mobility(duration="2 min", label="walk"),
            Check(Agreement(over="walk", lag="1 beacon")),
            Check(Flaps(over="walk")),
            Sleep("30 s"),
            Check(Lists(), during="2 beacons"),
        ],
    )
    lines: list[str] = []
    started = time.perf_counter()
    result = run(
        sc,
        run_dir=tmp_path,
        backend=replace(backend, clock=clock),
        say=quiet(lines),
        report=False,
    )
    real = time.perf_counter() - started
    assert result.ok, "\n".join(lines)
    assert [c.ok for c in result.checks] == [True] * 6
    # Two minutes of mobility, 30 s of sleep and 20 s of holding went by in virtual time.
    assert result.duration >= 120 + 30 + 20
    assert clock.monotonic() == pytest.approx(result.duration, abs=1.0)
    assert real < 30, f"{real:.1f} s of real time for a virtual run"
    walk = next(c for c in result.checks if c.kind == "agreement")
    samples = walk.data["agreement"]["samples"]
    assert 110 <= samples <= 125  # one sample a virtual second over the 2-minute walk
    moves = [c for c in labs[0].calls if c[0] == "move"]
    assert len(moves) == 6 * (int(120 / 0.5) + 1)  # every robot at every tick, on time


def test_a_deadline_is_counted_in_the_backend_s_time(
    fake: tuple[Backend, list[FakeLab]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    backend, _ = fake
    clock = _virtual(backend, monkeypatch)

    def make(spec: object) -> FakeLab:
        lab = backend.make_lab(spec)  # type: ignore[arg-type]
        lab.blind.add(("r1", "r2"))  # r1 never lists r2
        return lab

    sc = Scenario(
        "late",
        robots=3,
        beacon=PRODUCT_BEACON,
        capture="none",
        steps=[Start(), Check(Lists(), within="2 beacons"), Check(Unreachable("r3"), within=5)],
    )
    result = run(
        sc, run_dir=tmp_path, backend=replace(backend, make_lab=make, clock=clock), say=quiet([])
    )
    first, second = result.checks
    assert first.ok is False and "r1" in first.detail and "r2" in first.detail
    assert first.deadline == 20.0 and 20.0 < first.at < 20.5
    # r3 runs and is listed: not unreachable after 5 virtual seconds either.
    assert second.ok is False and second.at > first.at
    assert result.status == "failed" and result.duration < 30


def test_an_error_names_the_daemons_that_ended_though_no_step_stopped_them(
    fake: tuple[Backend, list[FakeLab]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A robot's API that stops answering is explained by its daemon's end (a crash, a kill
    from elsewhere), not left as a bare "cannot reach"; a robot a step stopped is not named."""
    backend, _ = fake
    clock = _virtual(backend, monkeypatch)
    real_start_all = FakeLab.start_all

    def start_all_then_crash(lab: FakeLab, *args: object, **kw: object) -> None:
        real_start_all(lab, *args, **kw)  # type: ignore[arg-type]
        lab.crash("r2")

    monkeypatch.setattr(FakeLab, "start_all", start_all_then_crash)
    sc = Scenario(
        "crash",
        robots=3,
        beacon=PRODUCT_BEACON,
        capture="none",
        steps=[Start(), Stop("r3"), Publish("all", "camera", "sensor.camera")],
    )
    result = run(sc, run_dir=tmp_path, backend=replace(backend, clock=clock), say=quiet([]))
    assert result.status == "error"
    assert result.error is not None
    assert "step 3 (publish)" in result.error
    assert "sdfrd ended though no step stopped it on r2 (signal 9 (SIGKILL))" in result.error
    assert "r3 (" not in result.error


def test_a_step_waits_out_a_robot_that_stalls_for_seconds_and_a_sample_does_not(
    fake: tuple[Backend, list[FakeLab]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The radio VM's emulated CPU stalled for 6 s in a publish (CI, 2026-11-29): a step's
    client waits that out (an action is no measurement), the observer's does not (a late
    sample is worth less than the next)."""
    backend, labs = fake
    clock = _virtual(backend, monkeypatch)
    waits: list[float] = []

    def connect(lab: FakeLab, robot: str, timeout: float) -> FakeClient:
        waits.append(timeout)
        lab.stall["r1"] = 6.0
        return FakeClient(lab, robot, timeout)

    sc = Scenario(
        "stall",
        robots=2,
        beacon=PRODUCT_BEACON,
        capture="none",
        steps=[Start(), Publish("r1", "camera", "sensor.camera"), Sleep("5 s")],
    )
    run_ = replace(backend, clock=clock, connect=connect)
    result = run(sc, run_dir=tmp_path, backend=run_, say=quiet([]))
    assert result.status == "passed", result.error
    assert labs[-1].services["r1"] == {"r1-camera": "camera"}
    assert min(waits) < 6.0 < max(waits)


def test_a_start_step_waits_as_long_as_it_says(
    fake: tuple[Backend, list[FakeLab]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A start step's `within` is how long its robots may take to be healthy (a radio robot
    joins its WiFi first); without it, 60 s or 2 s a robot."""
    backend, _ = fake
    clock = _virtual(backend, monkeypatch)
    waited: list[float] = []
    real_start_all = FakeLab.start_all

    def start_all(lab: FakeLab, refs: object = None, *, timeout: float = 60, **kw: object) -> None:
        waited.append(timeout)
        real_start_all(lab, refs, timeout=timeout, **kw)

    monkeypatch.setattr(FakeLab, "start_all", start_all)
    sc = Scenario(
        "slow-start",
        robots=2,
        beacon=PRODUCT_BEACON,
        capture="none",
        steps=[Start(["r1"], within="5 min"), Start(["r2"])],
    )
    result = run(sc, run_dir=tmp_path, backend=replace(backend, clock=clock), say=quiet([]))
    assert result.status == "passed", result.error
    assert waited == [300.0, 60.0]


class _Flapping(set[tuple[str, str]]):
    """r1 misses r2 while `gone(t)` says so, t counted on `clock` from its creation."""

    def __init__(self, clock: VirtualClock, gone: Callable[[float], bool]) -> None:
        super().__init__()
        self.clock, self.gone, self.t0 = clock, gone, clock.monotonic()

    def __iter__(self) -> Iterator[tuple[str, str]]:
        return iter([("r1", "r2")] if self.gone(self.clock.monotonic() - self.t0) else [])


@pytest.mark.parametrize(
    ("gone", "ok", "took"),
    [
        # Holds at 2 s, breaks at 3 s, holds for good from 5 s: steady 4 s is reached at 9 s.
        (lambda t: t < 2 or 3 <= t < 5, True, 5.0),
        # Never holds 4 s on end: it breaks every 3 s.
        (lambda t: t % 3 < 0.5, False, None),
        # Holds for good only from 12 s, after the 10 s deadline: too late to begin.
        (lambda t: t < 12, False, None),
    ],
)
def test_a_steady_check_counts_only_an_unbroken_stretch_begun_within_its_deadline(
    fake: tuple[Backend, list[FakeLab]],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    gone: Callable[[float], bool],
    ok: bool,
    took: float | None,
) -> None:
    backend, _ = fake
    clock = _virtual(backend, monkeypatch)

    def make(spec: object) -> FakeLab:
        lab = backend.make_lab(spec)  # type: ignore[arg-type]
        lab.blind = _Flapping(clock, gone)
        return lab

    sc = Scenario(
        "settle",
        robots=3,
        beacon=PRODUCT_BEACON,
        capture="none",
        steps=[Start(), Wait(Lists(), within="10 s", steady="4 s")],
    )
    lines: list[str] = []
    result = run(
        sc, run_dir=tmp_path, backend=replace(backend, make_lab=make, clock=clock), say=quiet(lines)
    )
    (check,) = result.checks
    assert check.ok is ok, "\n".join(lines)
    if took is None:
        assert check.took is None and "r1" in check.detail and result.status == "failed"
        assert result.duration < 20  # failed at its deadline, not later
    else:
        assert check.took == pytest.approx(took, abs=0.5)
        assert any("held steady 4 s" in line for line in lines), lines
