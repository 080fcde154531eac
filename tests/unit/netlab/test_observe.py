"""Flaps, indicators and daemon resources: the judging functions (pure) and the scenario
engine's checks built on them (on the fake lab of test_netlab_scenario)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from netlab import procstat
from netlab.judging import PeerEntry, View, history_problems, indicator_problems
from netlab.samples import Sample, flaps, indicators_before
from netlab.scenario import (
    Backend,
    Check,
    Duration,
    Flaps,
    Indicator,
    InHistory,
    Kill,
    Lists,
    Quality,
    Resources,
    Scenario,
    ScenarioError,
    Sleep,
    Start,
    Unreachable,
    Wait,
    loads,
    run,
)
from netlab.truth import TruthState
from tests.support.fakelab import BEACON, FakeLab, quiet

ALL = frozenset({("r1", "r2"), ("r2", "r1")})


def state(t: float, links: frozenset[tuple[str, str]] = ALL) -> TruthState:
    return TruthState(t, links, frozenset({"r1", "r2"}))


def seen(t: float, r1: set[str], r2: set[str] | None = None) -> Sample:
    return Sample(t, {"r1": frozenset(r1), "r2": frozenset(r2 if r2 is not None else {"r1"})})


# -- flaps ------------------------------------------------------------------------------------


def test_a_flap_is_a_linked_peer_dropped_between_two_samples() -> None:
    samples = [seen(t, {"r2"} if t not in (3, 4, 50) else set()) for t in range(0, 120)]
    stats = flaps(samples, [state(0)], per=60)
    assert stats.flaps == 2 and stats.at["r1"]["r2"] == [3.0, 50.0]
    assert stats.most == 2  # both within one minute
    assert stats.pairs == 2 and stats.samples == 120
    assert stats.worst == [("r1", "r2", 2)]
    # Counted per minute: 3 s and 70 s are never in one window of 60 s.
    samples = [seen(t, {"r2"} if t not in (3, 70) else set()) for t in range(0, 120)]
    assert flaps(samples, [state(0)], per=60).most == 1


def test_a_drop_the_medium_explains_is_no_flap() -> None:
    cut = state(10, frozenset())
    samples = [seen(t, {"r2"} if t < 11 or t > 20 else set()) for t in range(0, 30)]
    stats = flaps(samples, [state(0), cut, state(20)], per=60)
    assert stats.flaps == 0


def test_flaps_only_count_in_the_window_and_across_unanswered_samples() -> None:
    samples = [seen(t, {"r2"} if t != 5 else set()) for t in range(0, 10)]
    assert flaps(samples, [state(0)], start=6).flaps == 0
    # r1 did not answer at t=5 (absent from the sample): 4 -> 6 is no flap.
    samples = [
        Sample(t, {"r2": frozenset({"r1"})}) if t == 5 else seen(t, {"r2"}) for t in range(10)
    ]
    assert flaps(samples, [state(0)]).flaps == 0


# -- indicators -------------------------------------------------------------------------------


def view(**indicators: float | None) -> View:
    return View(tuple(PeerEntry(p, True, indicator=i) for p, i in indicators.items()))


def test_indicators_are_judged_against_the_round_trip_delivery() -> None:
    views = {"r1": view(r2=0.45, r3=0.2), "r2": view(r1=None), "r3": View(error="timed out")}
    rates = {("r1", "r2"): 0.49, ("r1", "r3"): 0.49, ("r2", "r1"): 0.49}
    assert indicator_problems(views, rates, 0.15) == [
        "r1 rates r3 at 0.20, the medium delivers 0.49 round trip (allowed: +-0.15)",
        "r2 has no indicator for r1 yet",
        "r3: timed out",
    ]
    assert indicator_problems({"r1": view(r2=0.6)}, rates, 0.15) == []


def test_the_indicator_must_fall_below_what_was_sampled_before() -> None:
    samples = [
        Sample(1.0, {"r1": frozenset({"r2"})}, {"r1": {"r2": 1.0}}),
        Sample(2.0, {"r1": frozenset({"r2"})}, {"r1": {"r2": 0.95}}),
        Sample(3.0, {"r1": frozenset()}, {"r1": {}}),
    ]
    before = indicators_before(samples, 2.5)
    assert before == {"r1": {"r2": 0.95}}
    assert indicators_before(samples, 1.0) == {}
    hist = {"r1": View((PeerEntry("r2", False, indicator=0.8),))}
    assert history_problems(hist, ["r2"], ["r1"], fell_from=before) == []
    hist = {"r1": View((PeerEntry("r2", False, indicator=0.95),))}
    assert history_problems(hist, ["r2"], ["r1"], fell_from=before) == [
        "r1's indicator for r2 did not fall: 0.95 now, 0.95 before"
    ]
    assert history_problems(hist, ["r2"], ["r1"], fell_from={}) == [
        "no indicator of r1 for r2 was sampled before"
    ]


def test_samples_keep_their_indicators_through_json() -> None:
    s = Sample(1.5, {"r1": frozenset({"r2"})}, {"r1": {"r2": 0.5}})
    assert Sample.from_json(s.to_json()) == s
    plain = Sample(1.5, {"r1": frozenset()})
    assert "indicators" not in plain.to_json() and Sample.from_json(plain.to_json()) == plain


# -- /proc ------------------------------------------------------------------------------------


def test_a_process_tree_and_its_cpu_and_memory() -> None:
    child = subprocess.Popen(
        [sys.executable, "-c", "import time; print('up', flush=True); time.sleep(30)"],
        stdout=subprocess.PIPE,
    )
    try:
        # Its start-up done (its CPU in the window would be a second core's: CI saw 0.36 s
        # of CPU in 0.305 s of wall time), it sleeps through the window.
        assert child.stdout is not None and child.stdout.readline() == b"up\n"
        kids = procstat.children()
        assert child.pid in procstat.tree(os.getpid(), kids)
        first = procstat.Usage.read([os.getpid(), child.pid])
        end = time.process_time() + 0.3
        while time.process_time() < end:
            pass
        last = procstat.Usage.read([os.getpid(), child.pid])
        used = procstat.window(first, last)
        assert used["processes"] == 2
        # The CPU spent is measured; its share of the wall time depends on how busy the
        # machine is, so only its arithmetic is checked (a loaded CI host gave 18 %).
        assert used["cpu_s"] >= 0.25 and used["wall_s"] >= used["cpu_s"] - 0.05
        assert used["cpu_percent"] == pytest.approx(100 * used["cpu_s"] / used["wall_s"], rel=0.02)
        assert 5 < used["rss_mib"] < 2000 and 0 < used["pss_mib"] <= used["rss_mib"]
    finally:
        child.kill()
        child.wait()
        if child.stdout is not None:
            child.stdout.close()
    gone = procstat.Usage.read([child.pid])  # a process that is gone counts for nothing
    assert gone.processes == 0 and gone.cpu_s == 0


def test_a_sdfrd_process_is_told_apart_by_its_name_not_its_shared_command_line(
    tmp_path: Path,
) -> None:
    def proc(pid: int, comm: str, cmdline: bytes) -> None:
        (tmp_path / str(pid)).mkdir()
        (tmp_path / str(pid) / "comm").write_text(comm + "\n")
        (tmp_path / str(pid) / "cmdline").write_bytes(cmdline)

    sdfrd = b"/venv/bin/python3\0/venv/bin/sdfrd\0--fleet\x003\0"
    proc(10, "sdfrd", sdfrd)
    proc(11, "sdfrd-api", sdfrd)  # forked: the supervisor's command line, its own name
    proc(12, "sdfrd-discovery", sdfrd)
    proc(13, "python3", b"python3\0-m\0sdfr.daemon\0")
    proc(14, "tcpdump", b"tcpdump\0-i\0eth0\0")
    layers = [procstat.layer_of(pid, tmp_path) for pid in (10, 11, 12, 13, 14, 15)]
    assert layers == ["supervisor", "api", "discovery", "supervisor", "other", "gone"]


# -- the scenario engine ----------------------------------------------------------------------


def test_flaps_indicator_falling_and_resources_checks_in_a_run(
    fake: tuple[Backend, list[FakeLab]], tmp_path: Path
) -> None:
    backend, _ = fake
    sc = Scenario(
        "lossy",
        robots=3,
        beacon=BEACON,
        sample=0.02,
        steps=[
            Quality("all", loss=30),
            Start(),
            Wait(Lists(), within="2 beacons"),
            Sleep(0.3, label="lossy"),
            Check(Flaps(over="lossy")),
            Check(Indicator(), within="1 beacon"),
            Check(Resources(over="lossy", cpu_at_most=1000.0)),
            Kill("r3"),
            Check(Unreachable("r3"), within="3 beacons"),
            Check(InHistory("r3", reachable=False, falling=True), within="1 beacon"),
        ],
    )
    lines: list[str] = []
    result = run(sc, run_dir=tmp_path, say=quiet(lines), backend=backend, report=False)
    assert result.ok, "\n".join(lines)
    by_kind = {c.kind: c for c in result.checks}
    assert by_kind["flaps"].data["flaps"]["flaps"] == 0
    assert by_kind["flaps"].data["flaps"]["pairs"] == 6
    ind = by_kind["indicator"].data
    assert ind["abs_error"] == {"mean": 0.0, "max": 0.0, "pairs": 6}
    assert ind["indicators"]["r1"]["r2"] == pytest.approx(0.49)
    res = by_kind["resources"].data
    assert res["daemons"] == 3 and set(res["per_daemon"]) == {"r1", "r2", "r3"}
    assert "CPU" in by_kind["resources"].detail


def test_a_wrong_indicator_and_a_resource_limit_fail_naming_the_robot(
    fake: tuple[Backend, list[FakeLab]], tmp_path: Path
) -> None:
    backend, labs = fake
    sc = Scenario(
        "wrong",
        robots=2,
        beacon=BEACON,
        steps=[
            Quality("all", loss=30),
            Start(),
            Sleep(0.05, label="busy"),
            Check(Indicator(tolerance=0.1), within="1 beacon"),
            Check(Resources(over="busy", pss_at_most=0.001)),
        ],
    )

    def make(spec: object) -> FakeLab:
        lab = FakeLab(spec)  # type: ignore[arg-type]
        lab.bias = {("r2", "r1"): 0.3}
        labs.append(lab)
        return lab

    from dataclasses import replace

    result = run(
        sc, run_dir=tmp_path, say=quiet([]), backend=replace(backend, make_lab=make), report=False
    )
    ind, res = result.checks
    assert ind.ok is False
    assert ind.detail.startswith(
        "r2 rates r1 at 0.79, the medium delivers 0.49 round trip (allowed: +-0.1)"
    )
    assert res.ok is False and "over the limit: r1 took" in res.detail


def test_the_new_checks_read_from_a_file_and_bad_fields_are_refused() -> None:
    text = """
[scenario]
name = "x"
robots = 2
[[step]]
start = "all"
label = "go"
[[step]]
check = "flaps"
over = "go"
at_most = 2
per = "30 s"
[[step]]
check = "indicator"
tolerance = 0.2
within = "1 beacon"
[[step]]
check = "resources"
over = "go"
cpu_at_most = 5
[[step]]
check = "history"
robots = "r2"
falling = true
within = 1
"""
    sc = loads(text)
    conds = [s.condition for s in sc.steps if isinstance(s, Check)]
    assert conds == [
        Flaps(at_most=2, per=Duration.of("30 s"), over="go"),
        Indicator(tolerance=0.2),
        Resources(over="go", cpu_at_most=5.0),
        InHistory("r2", falling=True),
    ]
    with pytest.raises(ScenarioError, match="at_most: must be >= 0"):
        loads(text.replace("at_most = 2", "at_most = -1"))
    with pytest.raises(ScenarioError, match="tolerance"):
        loads(text.replace("tolerance = 0.2", "tolerance = 2"))
    with pytest.raises(ScenarioError, match="no earlier step labelled"):
        loads(text.replace('over = "go"\nat_most', 'over = "nope"\nat_most'))
    with pytest.raises(ScenarioError, match="flaps check is judged once"):
        loads(text.replace('per = "30 s"', 'per = "30 s"\nwithin = 1'))
    with pytest.raises(ScenarioError, match="indicator check needs within"):
        loads(text.replace('tolerance = 0.2\nwithin = "1 beacon"', "tolerance = 0.2"))


def test_a_robot_s_answer_is_read_by_the_api_s_schema() -> None:
    """What a robot lists is decoded by the API's own schema (`sdfr.records.schema`), one
    definition for sdfrd and netlab: a well-formed answer becomes entries, and one that breaks
    the schema is an error naming the field, not a guess."""
    from typing import Any

    from netlab.observe import Probe

    good = {
        "robot_id": "r2",
        "address": "10.1.0.2",
        "reachable": True,
        "indicator": 0.9,
        "rtt_ms": 1.5,
        "last_seen": 1.0,
        "services": [
            {"id": "s1", "name": "camera", "type": "sensor.camera", "url": None, "attributes": {}}
        ],
    }

    class Answers:
        def __init__(self, entries: list[dict[str, Any]]) -> None:
            self.entries = entries

        def neighbors(self, include_unreachable: bool = False) -> list[dict[str, Any]]:
            return self.entries

        def close(self) -> None:
            pass

    answers = {"r1": Answers([good]), "r3": Answers([{**good, "reachable": "yes"}])}
    views = Probe(lambda robot: answers[robot]).neighbours(["r1", "r3"])  # type: ignore[arg-type,return-value]
    assert views["r1"].entries == (PeerEntry("r2", True, "10.1.0.2", frozenset({"camera"}), 0.9),)
    assert views["r3"].entries == ()
    error = views["r3"].error or ""
    assert "does not match the API's schema" in error and "reachable" in error, error
