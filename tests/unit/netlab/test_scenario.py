"""Scenarios without root: durations, TOML files and their errors, the judging functions, and
the engine run against a fake lab whose daemons list exactly the medium's truth."""

from __future__ import annotations

import json
import sys
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from netlab import cli
from netlab.errors import NetlabError
from netlab.judging import (
    PeerEntry,
    View,
    address_problems,
    expect_problems,
    history_problems,
    unreachable_problems,
)
from netlab.ranges import UnitDisc
from netlab.samples import Sample, agreement
from netlab.scenario import (
    Agreement,
    Backend,
    Check,
    Collision,
    Duration,
    InHistory,
    Kill,
    LabSpec,
    Lists,
    Medium,
    Merge,
    Mobility,
    Move,
    Partition,
    Publish,
    Quality,
    Restart,
    RunResult,
    Scenario,
    ScenarioError,
    Shape,
    Sleep,
    Start,
    Stop,
    Unpublish,
    Unreachable,
    Updates,
    Wait,
    add_robots,
    bundled,
    find,
    load,
    loads,
    missing_requirements,
    rebuild_report,
    run,
)
from netlab.truth import TruthState
from sdfr.protocol.addressing import candidates
from tests.support.fakelab import BEACON, FakeLab, quiet

# -- durations -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "seconds", "beacons"),
    [
        (2, 2.0, 0.0),
        (0.5, 0.5, 0.0),
        ("2 s", 2.0, 0.0),
        ("1.5s", 1.5, 0.0),
        ("500 ms", 0.5, 0.0),
        ("2 min", 120.0, 0.0),
        ("3 beacons", 0.0, 3.0),
        ("1 beacon", 0.0, 1.0),
        ("1 beacon + 1 s", 1.0, 1.0),
        ("3 beacons + 0.5 s", 0.5, 3.0),
        ("4", 4.0, 0.0),
    ],
)
def test_durations_are_read_in_seconds_or_beacons(
    text: str | float, seconds: float, beacons: float
) -> None:
    d = Duration.of(text)
    assert (d.seconds, d.beacons) == pytest.approx((seconds, beacons))


def test_deadlines_in_beacons_scale_with_the_beacon() -> None:
    d = Duration.of("3 beacons + 0.5 s")
    assert d.at(1.0) == pytest.approx(3.5)
    assert d.at(0.5) == pytest.approx(2.0)
    assert d.at(10.0) == pytest.approx(30.5)
    assert str(d) == "3 beacons + 0.5 s"
    assert str(Duration.of(2)) == "2 s"


@pytest.mark.parametrize("bad", ["3 parsecs", "beacons", "-1 s", "", True, -2, [1], "1 s +"])
def test_bad_durations_say_what_is_accepted(bad: Any) -> None:
    with pytest.raises(ValueError, match=r"duration|seconds|number"):
        Duration.of(bad)


# -- scenario files --------------------------------------------------------------------------

FULL = """
[scenario]
name = "full"
description = "every step"
robots = 4
beacon = 0.5
radius = 30
layout = "line"
spacing = 2.0

[groups]
a = ["r1", "r2"]
b = ["r3", "r4"]

[positions]
r4 = [5.0, 5.0]

[sdfrd]
miss_limit = 3

[[step]]
start = "all"
options = { ping_window = 10 }

[[step]]
publish = ["r1", "r2"]
service = "camera"
type = "sensor.camera"
attributes = { fps = 30 }

[[step]]
wait = "lists"
within = "2 s"

[[step]]
partition = ["a", "b"]
label = "split"

[[step]]
check = "lists"
groups = ["a", "b"]
within = "3 beacons + 0.5 s"

[[step]]
check = "history"
robots = "b"
on = "a"
reachable = false
during = "1 beacon"

[[step]]
merge = true
label = "merge"

[[step]]
move = "r4"
to = [40, 0]

[[step]]
check = "unreachable"
robots = "r4"
within = "3 beacons"

[[step]]
quality = ["r1", "r2"]
loss = 30

[[step]]
quality = "all"
loss = "none"

[[step]]
shape = "r1"
loss = 10
rate = "1mbit"

[[step]]
shape = "r1"

[[step]]
unpublish = "r2"
service = "camera"

[[step]]
stop = "r3"

[[step]]
kill = "r2"

[[step]]
restart = "r1"
hard = true

[[step]]
mobility = "running"
duration = "2 min"
quick = "10 s"
speed = [0.5, 1.0]
pause = 1
label = "walk"

[[step]]
check = "agreement"
over = "walk"
lag = "1 beacon"
loss_lag = "3 beacons"

[[step]]
check = "medium"
within = "1 beacon"

[[step]]
sleep = "2 beacons"
quick = 0.1

[[step]]
check = "updates"
after = "merge"
at_most = 2

[[step]]
collision = ["r1", "r3"]

[[step]]
check = "addresses"
within = 1
"""


def test_a_scenario_file_gives_the_steps_in_order_with_their_fields() -> None:
    sc = loads(FULL, "full.toml")
    assert sc.names == ("r1", "r2", "r3", "r4")
    assert sc.beacon == 0.5 and sc.radius == 30.0 and dict(sc.sdfrd) == {"miss_limit": 3}
    kinds = [s.kind for s in sc.steps]
    assert kinds == [
        "start", "publish", "wait", "partition", "check", "check", "merge", "move", "check",
        "quality", "quality", "shape", "shape", "unpublish", "stop", "kill", "restart",
        "mobility", "check", "check", "sleep", "check", "collision", "check",
    ]  # fmt: skip
    start, publish, wait = sc.steps[0], sc.steps[1], sc.steps[2]
    assert isinstance(start, Start) and dict(start.options) == {"ping_window": 10}
    assert isinstance(publish, Publish) and publish.robots == ("r1", "r2")
    assert dict(publish.attributes) == {"fps": 30}
    assert isinstance(wait, Wait) and isinstance(wait.condition, Lists)
    assert Duration.of(wait.within or 0).at(sc.beacon) == 2.0
    split = sc.steps[4]
    assert isinstance(split, Check) and not isinstance(split, Wait)
    assert isinstance(split.condition, Lists) and split.condition.groups == ("a", "b")
    assert Duration.of(split.within or 0).at(sc.beacon) == pytest.approx(2.0)
    hist = sc.steps[5]
    assert isinstance(hist, Check) and isinstance(hist.condition, InHistory)
    assert hist.condition.reachable is False and hist.within is None
    move = sc.steps[7]
    assert isinstance(move, Move) and move.to == (40.0, 0.0)
    q1, q2 = sc.steps[9], sc.steps[10]
    assert isinstance(q1, Quality) and q1.loss == 30.0 and q1.both
    assert isinstance(q2, Quality) and q2.loss is None
    shape, unshape = sc.steps[11], sc.steps[12]
    assert isinstance(shape, Shape) and dict(shape.params) == {"loss": 10, "rate": "1mbit"}
    assert isinstance(unshape, Shape) and dict(unshape.params) == {}
    restart = sc.steps[16]
    assert isinstance(restart, Restart) and restart.hard
    walk = sc.steps[17]
    assert isinstance(walk, Mobility) and walk.pause == (1.0, 1.0) and walk.label == "walk"
    agree = sc.steps[18]
    assert isinstance(agree, Check) and isinstance(agree.condition, Agreement)
    assert agree.condition.over == "walk"
    assert sc.collisions() == [("r1", "r3")]
    assert sc.initial_positions() == {
        "r1": (0.0, 0.0),
        "r2": (2.0, 0.0),
        "r3": (4.0, 0.0),
        "r4": (5.0, 5.0),
    }


def test_the_bundled_scenarios_load() -> None:
    names = set(bundled())
    assert {"static-2", "static-4", "static-6", "partition-merge", "mobility"} <= names
    assert {"silent-departure", "ip-collision"} <= names
    for name, path in bundled().items():
        sc = load(path)
        assert sc.name == name
        if sc.beacon != 10.0:  # the product's, or short beacons said so in the file
            assert sc.beacon in (1.0, 2.0) and "product default is 10 s" in path.read_text()
    assert find("mobility") == bundled()["mobility"]
    with pytest.raises(ScenarioError, match="no bundled scenario of that name"):
        find("nosuch")


def test_the_collision_scenario_is_skipped_without_sdfrd_addressing() -> None:
    sc = load(bundled()["ip-collision"])
    assert sc.addressing == "auto" and sc.collisions() == [("r2", "r4")]
    reason = missing_requirements(sc, frozenset({"beacon_interval", "miss_limit"}))
    assert reason is not None and "--addressing" in reason and "collision" in reason
    assert missing_requirements(sc, frozenset({"beacon_interval", "addressing"})) is None


BASE = """
[scenario]
name = "bad"
robots = 3
[groups]
a = ["r1", "r2"]
"""


@pytest.mark.parametrize(
    ("steps", "message"),
    [
        ('kill = "r9"', r"bad\.toml: step 1 \(kill\): robots: unknown robot or group 'r9'"),
        ('kill = "r1"\ncolour = "red"', r"step 1 \(kill\): unknown field colour \(this takes"),
        ('kill = "r1"\nstart = "r2"', r"step 1: more than one action \(kill, start\)"),
        ('robots = "r1"', r"step 1: no action; a step has one of: start, stop"),
        ('check = "lists"', r"step 1 \(check\): a lists check needs within"),
        ('check = "lists"\nwithin = "3 parsecs"', r"step 1 \(check\): within: cannot read"),
        ('check = "lists"\nwithin = 1\ngroups = ["a", "r1"]', r"groups: robots in more than"),
        ('check = "smiles"\nwithin = 1', r"step 1 \(check\): check: unknown condition 'smiles'"),
        ('check = "agreement"\nwithin = 1', r"agreement check is judged once"),
        ('check = "lists"\nduring = 1\nsteady = 2', r"step 1 \(check\): steady needs within"),
        ('check = "lists"\nwithin = 1\nsteady = "soon"', r"step 1 \(check\): steady: cannot"),
        ('check = "agreement"', r"step 1 \(check\): over: no action step before it"),
        ('partition = ["a"]\n[[step]]\ncheck = "updates"\nafter = "x"', r"step 2.*after: no"),
        ('quality = ["r1", "r2"]\nloss = 120', r"step 1 \(quality\): loss: must be 0-100"),
        ('quality = "r1"\nloss = 1', r"names no pair"),
        ('shape = "r1"\ndelay = -5', r"step 1 \(shape\): .*delay"),
        ('shape = "r1"\nwarp = 5', r"step 1 \(shape\): unknown field warp"),
        ('collision = ["r1"]', r"step 1 \(collision\): robots: needs two or more"),
        ('move = "r1"\nto = [1]', r"step 1 \(move\): to: expected \[x, y\]"),
        ('mobility = "all"\nduration = 5\nspeed = [0, 1]', r"speed: the minimum must be above"),
        ('merge = "yes"', r"step 1 \(merge\): merge: write `= true`"),
        ('sleep = 1\nlabel = "x"\n[[step]]\nsleep = 1\nlabel = "x"', r"step 2 .*already the"),
        ('start = "all"\noptions = { beacon_interval = 2 }', r"beacon_interval is set by the"),
        ('publish = "r1"\nservice = "cam"', r"step 1 \(publish\): type: missing"),
    ],
)
def test_bad_steps_are_refused_naming_the_step_and_the_field(steps: str, message: str) -> None:
    with pytest.raises(ScenarioError, match=message):
        loads(f"{BASE}\n[[step]]\n{steps}\n", "bad.toml")


@pytest.mark.parametrize(
    ("head", "message"),
    [
        ('name = "x"\nrobots = 0', r"robots: must be 1-"),
        ('name = "x"\nrobots = ["r1", "r1"]', r"robots: names repeat"),
        ('name = "x"\nrobots = ["R 1"]', r"robots: robot name 'R 1'"),
        ('name = "x"\nbeacon = 0', r"beacon: must be >= 0.01"),
        ('name = "x"\ncapture = "some"', r"capture: one of all, robots, medium, none"),
        ('name = "x"\naddressing = "dhcp"', r"addressing: one of manual, auto"),
        ('name = "x"\nruntime = "podman"', r"runtime: one of namespace, docker, got 'podman'"),
        ('name = "x"\nlayout = "circle"', r"layout: one of line, random"),
        ('name = "x"\nmedium = "ether"', r"medium: one of wired, radio, got 'ether'"),
        ('name = "x"\nair_medium = "wmediumd"', r"air_medium: one of netlab, hwsim, got 'wm"),
        ('name = "x"\nspeed = 2', r"\[scenario\]: unknown field speed"),
        ('name = "no spaces"', r"name: 1-64 of letters"),
    ],
)
def test_bad_scenario_tables_are_refused(head: str, message: str) -> None:
    with pytest.raises(ScenarioError, match=message):
        loads(f"[scenario]\n{head}\n", "bad.toml")


def test_other_file_errors() -> None:
    with pytest.raises(ScenarioError, match=r"bad\.toml: not valid TOML: .*line 2"):
        loads("[scenario]\nname = \n", "bad.toml")
    with pytest.raises(ScenarioError, match=r"unknown table or key 'steps'"):
        loads('[scenario]\nname = "x"\n[[steps]]\nstart = "all"\n', "bad.toml")
    with pytest.raises(ScenarioError, match=r"bad\.toml: groups: 'r1' is a robot name"):
        loads('[scenario]\nname = "x"\n[groups]\nr1 = ["r2"]\n', "bad.toml")
    with pytest.raises(ScenarioError, match=r"\[sdfrd\].*|sdfrd: robot_id is set by the lab"):
        loads('[scenario]\nname = "x"\n[sdfrd]\nrobot_id = "a"\n', "bad.toml")
    with pytest.raises(ScenarioError, match=r"cannot read scenario file"):
        load(Path("/nonexistent/x.toml"))


def test_the_python_api_is_validated_like_files() -> None:
    with pytest.raises(ScenarioError, match=r"scenario 'x': step 2 \(kill\): robots: unknown"):
        Scenario("x", robots=2, steps=[Start(), Kill("r3")])
    with pytest.raises(ScenarioError, match=r"step 1 \(check\): a medium check needs within"):
        Scenario("x", steps=[Check(Medium())])
    with pytest.raises(ScenarioError, match=r"step 1: expected a Step"):
        Scenario("x", steps=["start"])  # type: ignore[list-item]
    sc = Scenario("x", robots=["a", "b"], steps=[Start(), Wait(Lists(), within="1 beacon")])
    assert sc.names == ("a", "b")


# -- judging snapshots and samples -----------------------------------------------------------


def view(*peers: str, services: Mapping[str, set[str]] | None = None, **kw: Any) -> View:
    entries = tuple(
        PeerEntry(p, True, f"10.1.0.{p[-1]}", frozenset((services or {}).get(p, ())), **kw)
        for p in peers
    )
    return View(entries)


def test_lists_problems_say_who_misses_what() -> None:
    views = {"r1": view("r2", "r3"), "r2": view("r1"), "r3": view("r1", "r2", "r2")}
    expected = {r: {"r1", "r2", "r3"} - {r} for r in views}
    assert expect_problems(views, expected) == [
        "r2 lists {r1} but should list {r1, r3}",
        "r3 lists r2 more than once",
    ]
    assert expect_problems(views, {"r2": {"r1", "r3"}}, exact=False) == [
        "r2 lists {r1}, without {r3}"
    ]
    with_services = {"r1": view("r2", services={"r2": {"camera"}})}
    problems = expect_problems(with_services, {"r1": {"r2"}}, services={"r2": {"camera", "lidar"}})
    assert problems == ["r1 lists r2 with services {camera}, but r2 publishes {camera, lidar}"]
    assert expect_problems({"r1": View(error="cannot reach sdfrd")}, {"r1": set()}) == [
        "r1: cannot reach sdfrd"
    ]


def test_unreachable_history_and_address_problems() -> None:
    views = {"r1": view("r2", "r3"), "r2": view("r1")}
    assert unreachable_problems(views, ["r3"], ["r1", "r2"]) == ["r1 still lists {r3} as reachable"]
    hist = {
        "r1": View((PeerEntry("r3", True, indicator=0.9),)),
        "r2": View((PeerEntry("r1", True),)),
    }
    assert history_problems(hist, ["r3"], ["r1", "r2"], reachable=False) == [
        "r1's history has r3 as reachable",
        "{r3} missing from the history of r2",
    ]
    assert history_problems(hist, ["r3"], ["r1"], indicator_below=0.5) == [
        "r1 rates r3 at indicator 0.9, not below 0.5"
    ]
    clash = {
        "r1": View((PeerEntry("r2", True, "10.1.0.7"), PeerEntry("r3", True, "10.1.0.7"))),
    }
    assert address_problems(clash, {"r1": "10.1.0.1", "r4": ""}) == [
        "r4 has no address yet",
        "{r2, r3} are listed at the same address 10.1.0.7",
    ]


def truth(t: float, links: set[tuple[str, str]], running: str = "abc") -> TruthState:
    return TruthState(t, frozenset(links), frozenset(running))


ALL = {(x, y) for x in "abc" for y in "abc" if x != y}


def test_agreement_allows_a_lag_and_a_longer_one_for_lost_links() -> None:
    # a and c lose each other at t=10; c still lists a until 12.5, a drops c at 10.5.
    states = [truth(0, ALL), truth(10, ALL - {("a", "c"), ("c", "a")})]
    samples = [
        Sample(9.0, {"a": frozenset("bc"), "b": frozenset("ac"), "c": frozenset("ab")}),
        Sample(10.5, {"a": frozenset("b"), "b": frozenset("ac"), "c": frozenset("ab")}),
        Sample(12.5, {"a": frozenset("b"), "b": frozenset("ac"), "c": frozenset("ab")}),
        Sample(13.0, {"a": frozenset("b"), "b": frozenset("ac"), "c": frozenset("b")}),
    ]
    strict = agreement(samples, states, lag=0.0)
    assert strict.observations == 24 and strict.stale == 2 and strict.missing == 0
    assert strict.pair_share == pytest.approx(22 / 24)
    assert strict.sample_share == pytest.approx(2 / 4)
    assert strict.worst[0][:2] == ("c", "a")
    one = agreement(samples, states, lag=1.0)  # c's entry at 12.5 is 2.5 s stale
    assert one.stale == 1 and one.sample_share == pytest.approx(3 / 4)
    lost = agreement(samples, states, lag=1.0, loss_lag=3.0)
    assert lost.pair_share == 1.0 and lost.sample_share == 1.0
    window = agreement(samples, states, lag=0.0, start=10.0, end=11.0)
    assert window.samples == 1 and window.stale == 1
    per = strict.per_sample[1]
    assert per.time == 10.5 and per.per_robot["a"] == 1.0 and per.per_robot["c"] == 0.5


def test_a_new_link_not_listed_in_time_is_missing() -> None:
    states = [truth(0, set()), truth(5, {("a", "b"), ("b", "a")})]
    samples = [Sample(5.5, {"a": frozenset(), "b": frozenset()})]  # c runs, is not asked
    assert agreement(samples, states, lag=1.0).missing == 0
    late = agreement(samples, states, lag=0.2)
    assert late.observations == 4 and late.missing == 2 and late.pair_share == 0.5


def test_a_robot_that_does_not_run_should_be_listed_by_nobody() -> None:
    state = truth(0, ALL, running="ab")
    assert state.expected("a") == {"b"} and state.expected("c") == set()
    assert not state.hears("c", "a")


# -- the engine, on a fake lab ---------------------------------------------------------------


def test_every_step_runs_in_order_and_every_check_passes(
    fake: tuple[Backend, list[FakeLab]], tmp_path: Path
) -> None:
    backend, labs = fake
    sc = Scenario(
        "all-steps",
        robots=4,
        beacon=BEACON,
        radius=20.0,
        groups={"a": ["r1", "r2"], "b": ["r3", "r4"]},
        sample=0.02,
        steps=[
            Start(),
            Publish("all", "camera", "sensor.camera"),
            Wait(Lists(), within="2 beacons"),
            Partition(["a", "b"], label="split"),
            Check(Lists(groups=["a", "b"]), within="3 beacons"),
            Check(InHistory("b", on="a", reachable=False), during="1 beacon"),
            Merge(label="merge"),
            Check(Lists(), within=1),
            Move("r4", (100.0, 0.0)),
            Check(Unreachable("r4"), within="3 beacons"),
            Check(Medium(services=True), within=1),
            Move("r4", (3.0, 0.0)),
            Quality(["r1", "r2"], loss=100),
            Check(Lists(robots=["r1", "r2"]), within=0.2),  # fails: the pair is cut
            Quality("all", loss=None),
            Shape("r1", {"loss": 5}),
            Shape("r1"),
            Unpublish("r2", "camera"),
            Check(Lists(), within=1),
            Stop("r3"),
            Kill("r2"),
            Check(Lists(), within=1),
            Restart("r2", hard=True),
            Restart("r1"),
            Mobility(duration=0.5, tick=0.1, label="walk"),
            Check(Agreement(at_least=1.0, lag="1 beacon", over="walk")),
            Sleep(0.05),
            Check(Updates(after="merge")),
        ],
    )
    lines: list[str] = []
    result = run(sc, run_dir=tmp_path / "run", say=quiet(lines), backend=backend, report=False)
    assert result.status == "failed", "\n".join(lines)
    failed = result.failed
    assert [c.step for c in failed] == [14]
    assert failed[0].detail == (
        "r1 lists {r3, r4} but should list {r2}; r2 lists {r3, r4} but should list {r1}"
    )
    assert all(c.ok for c in result.checks if c.step != 14 and c.kind != "updates")
    updates = result.checks[-1]
    assert updates.ok is None and "needs captures" in updates.detail  # no captures: not judged
    lab = labs[0]
    ops = [c[0] for c in lab.calls]
    assert ops[:4] == ["start"] * 4 and all(c[2] == BEACON for c in lab.calls[:4])
    rest = [op for op in ops[4:] if op != "move"]
    assert rest == [
        "partition", "merge", "quality", "quality", "quality", "quality", "quality",
        "quality", "quality", "shape", "shape", "stop", "kill", "start", "restart",
    ]  # fmt: skip
    assert ("quality", "r1", "r2", 100, True) in lab.calls
    moves = [c for c in lab.calls if c[0] == "move"]
    assert moves[:2] == [("move", "r4"), ("move", "r4")] and len(moves) > 2  # then mobility
    saved = json.loads((tmp_path / "run" / "run.json").read_text())
    assert saved["meta"]["status"] == "failed" and len(saved["meta"]["checks"]) == len(
        result.checks
    )
    assert saved["samples"] and saved["truth"]
    assert any("FAIL  {r1, r2} list each other" in line for line in lines)
    assert any("FAILED" in line and "r1, r2" in line for line in lines)  # the summary table


def test_a_failed_wait_ends_the_run_and_says_who_missed_what(
    fake: tuple[Backend, list[FakeLab]], tmp_path: Path
) -> None:
    backend, labs = fake
    sc = Scenario(
        "blind",
        robots=3,
        beacon=BEACON,
        steps=[Start(), Wait(Lists(), within="2 beacons"), Kill("r1")],
    )

    def make(spec: LabSpec) -> FakeLab:
        lab = FakeLab(spec)
        lab.blind = {("r3", "r2")}
        labs.append(lab)
        return lab

    lines: list[str] = []
    result = run(
        sc,
        run_dir=tmp_path,
        say=quiet(lines),
        backend=replace(backend, make_lab=make),
        report=False,
    )
    assert result.status == "failed" and not result.ok
    (check,) = result.checks
    assert check.ok is False and check.deadline == pytest.approx(2 * BEACON)
    assert check.detail == "r3 lists {r1} but should list {r1, r2}"
    assert ("kill", "r1") not in labs[0].calls  # the run stopped at the wait
    assert any("stopping: step 2 (wait) failed" in line for line in lines)


def test_a_step_that_cannot_be_done_is_an_error_naming_it(
    fake: tuple[Backend, list[FakeLab]], tmp_path: Path
) -> None:
    backend, _ = fake
    sc = Scenario("oops", robots=2, beacon=BEACON, steps=[Start(), Unpublish("r1", "camera")])
    result = run(sc, run_dir=tmp_path, say=quiet([]), backend=backend, report=False)
    assert result.status == "error"
    assert result.error is not None
    assert result.error.startswith("step 2 (unpublish): r1 has no service 'camera'")
    again = Scenario("again", robots=2, beacon=BEACON, steps=[Start(), Start("r1")])
    result = run(again, run_dir=tmp_path, say=quiet([]), backend=backend, report=False)
    assert result.status == "error" and "step 2 (start): sdfrd already runs" in str(result.error)


def test_a_scenario_needing_an_option_sdfrd_lacks_is_skipped_saying_why(
    fake: tuple[Backend, list[FakeLab]], tmp_path: Path
) -> None:
    backend, labs = fake
    sc = Scenario(
        "collide",
        robots=3,
        addressing="auto",
        steps=[Collision(["r1", "r2"]), Start(), Check(Lists(), within=1)],
    )
    lines: list[str] = []
    result = run(sc, run_dir=tmp_path, say=quiet(lines), backend=backend)
    assert result.status == "skipped" and not result.ok and not labs
    assert result.reason is not None and "--addressing" in result.reason
    assert any("SKIPPED" in line and "--addressing" in line for line in lines)


def test_a_collision_gives_the_robots_one_derived_address(
    fake: tuple[Backend, list[FakeLab]], tmp_path: Path
) -> None:
    backend, labs = fake
    sc = Scenario("macs", robots=4, beacon=BEACON, steps=[Collision(["r2", "r4"]), Start()])
    lines: list[str] = []
    result = run(sc, run_dir=tmp_path, say=quiet(lines), backend=backend, report=False)
    assert result.ok
    macs = {n: r.mac for n, r in labs[0].robots.items()}
    # Different MACs (ARP must tell the two robots apart) deriving one first address.
    assert len(set(macs.values())) == 4 and macs["r2"][-5:] == macs["r4"][-5:]
    assert next(candidates(1, macs["r2"])) == next(candidates(1, macs["r4"]))
    assert any("MACs ending alike" in line and "addressing = auto" in line for line in lines)


def test_quick_runs_use_the_quick_durations(
    fake: tuple[Backend, list[FakeLab]], tmp_path: Path
) -> None:
    backend, labs = fake
    sc = Scenario(
        "quick",
        robots=2,
        beacon=BEACON,
        steps=[Start(), Mobility(duration="2 min", quick=0.2, tick=0.1), Sleep(60, quick=0.01)],
    )
    result = run(sc, run_dir=tmp_path, say=quiet([]), backend=backend, report=False, quick=True)
    assert result.ok and result.duration < 10
    assert sum(1 for c in labs[0].calls if c[0] == "move") == 2 * 3  # t = 0, 0.1, 0.2


def test_the_report_is_written_and_rebuilt_from_the_run_folder(
    fake: tuple[Backend, list[FakeLab]], tmp_path: Path
) -> None:
    pytest.importorskip("matplotlib")
    backend, _ = fake
    sc = Scenario(
        "report",
        robots=3,
        beacon=BEACON,
        sample=0.02,
        steps=[Start(), Sleep(0.2, label="stay"), Check(Agreement(over="stay"))],
    )
    result = run(sc, run_dir=tmp_path, say=quiet([]), backend=backend)
    assert result.ok and result.report is not None
    meta = result.report["meta"]
    assert meta["scenario"] == "report" and meta["status"] == "passed"
    assert [c["result"] for c in meta["checks"]] == ["ok"]
    assert meta["checks"][0]["data"]["agreement"]["pair_share"] == 1.0
    assert result.report["agreement"]["mean"] == 1.0
    assert {"connectivity", "agreement"} <= set(result.report["plots"])
    (tmp_path / "report.json").unlink()
    again = rebuild_report(tmp_path)
    assert again["meta"]["checks"] == meta["checks"]
    assert (tmp_path / "agreement.png").exists()


def test_summary_lines() -> None:
    res = RunResult("x", "passed", checks=[], duration=1.0)
    assert res.summary()[-1] == "x: PASSED, 0 of 0 checks ok, in 1.0 s"


# -- the command line (nothing here needs root) ----------------------------------------------


def test_cli_lists_the_bundled_scenarios(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["run", "--list"]) == 0
    out = capsys.readouterr().out
    for name in bundled():
        assert name in out
    # How long each takes, in full and with --quick: static-6 holds its check for 5 minutes.
    line = next(line for line in out.splitlines() if line.startswith("static-6 "))
    assert "5.0 min" in line and "15 s-18 s" in line


def test_a_scenario_knows_how_long_its_steps_take() -> None:
    sc = loads(
        "[scenario]\nbeacon = 2.0\n[[step]]\nsleep = 10\nquick = 1\n"
        '[[step]]\ncheck = "lists"\nwithin = "3 beacons"\nduring = 4\n'
        '[[step]]\nmobility = "all"\nduration = "1 min"\nquick = 5\n',
        "t.toml",
        name="t",
    )
    assert sc.timeline() == (74.0, 80.0)
    assert sc.timeline(quick=True) == (10.0, 16.0)


def test_kinds_give_robots_another_runtime_and_are_checked() -> None:
    sc = loads(
        '[scenario]\nrobots = 3\nruntime = "docker"\n[kinds]\nr2 = "namespace"\n', "k", name="k"
    )
    assert [sc.runtime_of(r) for r in sc.names] == ["docker", "namespace", "docker"]
    with pytest.raises(ScenarioError, match="kinds: unknown robot 'r9'"):
        loads('[scenario]\nrobots = 3\n[kinds]\nr9 = "docker"\n', "k", name="k")
    with pytest.raises(ScenarioError, match="kinds: r1: one of namespace, docker, got 'vm'"):
        loads('[scenario]\nrobots = 3\n[kinds]\nr1 = "vm"\n', "k", name="k")


def test_hosts_place_robots_or_groups_once_each_and_the_rest_are_spread() -> None:
    from netlab.spanlab import SpanLab, scenario_backend

    text = (
        '[scenario]\nrobots = 6\n[groups]\nleft = ["r1", "r2"]\n'
        '[hosts]\nh1 = "left"\n"root@10.0.0.3" = ["r5"]\nh3 = []\n'
    )
    sc = loads(text, "h.toml", name="h")
    assert sc.placement() == {"r1": "h1", "r2": "h1", "r5": "root@10.0.0.3"}
    # --hosts naming other hosts: placements on hosts not named are dropped (spread instead).
    spec = LabSpec("h", 0, 1, UnitDisc(10.0))
    lab = scenario_backend(sc, hosts=["h1", "h9"]).make_lab(spec)
    assert isinstance(lab, SpanLab)
    assert [s.destination for s, _ in lab.hosts] == ["h1", "h9"]
    assert dict(lab.place) == {"r1": "h1", "r2": "h1"}
    # `netlab run --hosts` (and the doctor's) goes through the same check as [hosts]: ssh
    # would read this one as an option.
    with pytest.raises(NetlabError, match="'-oProxyCommand=x' is not an ssh destination"):
        scenario_backend(sc, hosts=["h1", "-oProxyCommand=x"])
    for bad, said in (
        ('h1 = ["r1"]\nh2 = "left"', "hosts: r1 is on h1 and on h2: one host each"),
        ('"-oProxyCommand=x" = []', "hosts: '-oProxyCommand=x' is not an ssh destination"),
        ('h1 = ["r9"]', "hosts: h1: unknown robot or group 'r9'"),
        ("h1 = 3", r"\[hosts\]: h1: expected a robot, a group or a list of them"),
    ):
        with pytest.raises(ScenarioError, match=said):
            loads(text.split("[hosts]")[0] + "[hosts]\n" + bad + "\n", "h.toml", name="h")
    with pytest.raises(ScenarioError, match=r"unknown table or key 'host' \(did you mean 'hosts'"):
        loads("[scenario]\nrobots = 2\n[host]\nh1 = []\n", "h.toml", name="h")


def test_a_topology_file_lays_out_the_medium_only() -> None:
    from netlab.scenario import check_layout, lay_out

    sc = loads(
        "[scenario]\nrobots = 3\nradius = 10\n[positions]\nr3 = [30, 0]\n"
        '[[step]]\nquality = ["r1", "r2"]\nloss = 20\n[[step]]\npartition = [["r1"]]\n',
        "topo.toml",
        name="topo",
    )
    lab = FakeLab(LabSpec("t", 0, 1, UnitDisc(10.0)))
    add_robots(lab, sc)
    assert lay_out(lab, sc) == ["quality: 20 % loss on 1 pair", "partition r1"]
    assert lab.links() == {}  # r1 cut off, r3 out of range: r2 alone
    timeline = loads("[scenario]\nrobots = 2\n[[step]]\nstart = 'all'\n", "run.toml", name="run")
    with pytest.raises(ScenarioError, match=r"step 1 \(start\): a topology's steps lay out"):
        check_layout(timeline)


def test_cli_refuses_a_bad_scenario_file_with_status_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[scenario]\nname = "bad"\nrobots = 2\n[[step]]\nkill = "r5"\n')
    assert cli.main(["run", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "bad.toml: step 1 (kill): robots: unknown robot or group 'r5'" in err
    assert cli.main(["run", "nosuch"]) == 2
    assert "no bundled scenario" in capsys.readouterr().err
    assert cli.main(["report", str(tmp_path)]) == 1
    assert "neither captures" in capsys.readouterr().err


def test_without_the_netlab_extra_a_run_says_what_to_install(
    fake: tuple[Backend, list[FakeLab]],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    backend, _ = fake
    for module in ("matplotlib", "matplotlib.figure", "scapy", "scapy.utils", "scapy.error"):
        monkeypatch.setitem(sys.modules, module, None)  # as if not installed
    lines: list[str] = []
    sc = Scenario("tiny", robots=2, beacon=BEACON, steps=[Start()])
    result = run(sc, runs=tmp_path, say=lines.append, backend=backend)
    assert result.ok
    assert any(
        "report not written: the report needs the 'netlab' extra (matplotlib is not installed)"
        ": pip install 'sdfr-robots[netlab]'" in line
        for line in lines
    ), lines
    (folder,) = tmp_path.iterdir()
    assert cli.main(["report", str(folder)]) == 1
    assert "netlab report needs the 'netlab' extra" in capsys.readouterr().err
