"""Scenario steps against the real kernel and real sdfrd daemons (needs root), beacon 0.5 s;
and the `lab`/`fleet` fixtures, and `netlab run/capture/report`."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from netlab import cli, kernel, naming, pcap
from netlab.doctor import capabilities
from netlab.lab import Lab
from netlab.scenario import (
    Agreement,
    Check,
    Collision,
    InHistory,
    Kill,
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
    Shape,
    Sleep,
    Start,
    Stop,
    Unpublish,
    Unreachable,
    Updates,
    Wait,
    run,
)
from sdfr.errors import ApiError
from sdfr.protocol.addressing import candidates
from tests.support.fleets import unique_lab_name

pytestmark = pytest.mark.root

BEACON = 0.5
GONE = "3 beacons + 0.5 s"  # sdfrd's miss limit, plus timers and polling


def go(sc: Scenario, tmp_path: Path, *, status: str = "passed", **kw: Any) -> RunResult:
    lines: list[str] = []
    kw.setdefault("report", False)
    kw.setdefault("capture", "none")
    result = run(
        sc,
        run_dir=tmp_path / sc.name,
        lab_name=unique_lab_name(),
        say=lines.append,
        **kw,
    )
    assert result.status == status, "\n".join(lines)
    return result


def test_daemon_steps_start_publish_stop_kill_restart(tmp_path: Path) -> None:
    sc = Scenario(
        "life",
        robots=3,
        beacon=BEACON,
        steps=[
            Start(),
            Publish("all", "camera", "sensor.camera", attributes={"fps": 30}),
            Wait(Lists(), within="2 s"),
            Publish("r1", "lidar", "sensor.lidar"),
            Check(Lists(), within="500 ms"),  # churn is seen at once, with services
            Unpublish("r1", "lidar"),
            Check(Lists(), within="500 ms"),
            Stop("r3"),
            Check(Unreachable("r3"), within="1 beacon"),  # Byebye, not silence
            Check(InHistory("r3", reachable=False), during="1 beacon"),
            Start("r3"),
            Check(Lists(), within="1 s"),  # a join is listed by all, and lists all
            Kill("r2"),
            Check(Unreachable("r2"), within=GONE),
            Check(InHistory("r2", reachable=False), within="1 beacon"),
            Restart("r2", hard=True),
            Check(Lists(), within="1 s"),
            Restart("r1"),
            Check(Lists(), within="2 s"),
        ],
    )
    result = go(sc, tmp_path)
    assert len(result.checks) == 10 and all(c.ok for c in result.checks)
    byebye = result.checks[3]
    assert byebye.took is not None and byebye.took < BEACON
    silent = result.checks[6]
    assert silent.took is not None and silent.took > BEACON  # silence takes beacons
    assert (tmp_path / "life" / "logs" / "r2.log").exists()


def test_medium_steps_partition_merge_move_quality_shape(tmp_path: Path) -> None:
    sc = Scenario(
        "medium",
        robots=3,
        beacon=BEACON,
        radius=10.0,
        groups={"one": ["r1"], "two": ["r2", "r3"]},
        steps=[
            Start(),
            Wait(Medium(), within="2 s"),
            Partition(["one", "two"]),
            Check(Lists(groups=["one", "two"]), within=GONE),
            Merge(),
            Check(Lists(), within="1 beacon + 1 s"),
            Move("r3", (50.0, 0.0)),
            Check(Medium(), within=GONE),
            Check(Unreachable("r3", on=["r1", "r2"]), within="1 beacon"),
            Move("r3", (2.0, 0.0)),
            Check(Medium(), within="1 beacon + 1 s"),
            Quality(["r1", "r3"], loss=100),
            Check(Medium(), within=GONE),
            Quality(["r1", "r3"], loss=None),
            Check(Medium(), within="1 beacon + 1 s"),
            Shape("r2", {"loss": 100}),
            Check(Unreachable("r2"), within=GONE),
            Shape("r2"),
            Check(Lists(), within="1 beacon + 1 s"),
            Sleep(0.1),
        ],
    )
    result = go(sc, tmp_path)
    assert all(c.ok for c in result.checks)


def test_mobility_captures_agreement_updates_and_report(tmp_path: Path) -> None:
    pytest.importorskip("scapy")
    pytest.importorskip("matplotlib")
    sc = Scenario(
        "walk",
        robots=3,
        beacon=BEACON,
        radius=8.0,
        layout="random",
        seed=3,
        steps=[
            Start(),
            Publish("all", "camera", "sensor.camera"),
            Wait(Medium(services=True), within="2 s"),
            Mobility(duration=3, tick=0.5, label="walk"),
            Check(Agreement(at_least=0.95, lag="1 beacon", loss_lag=GONE, over="walk")),
            Partition([["r1"]]),
            Check(Medium(), within=GONE),
            Merge(label="merge"),
            # Not services=True: sdfrd may list a robot met during the walk without its
            # services (a protocol bug, reported separately).
            Check(Medium(), within="1 beacon + 1 s"),
            Sleep("1 beacon"),
            Check(Updates(after="merge")),
        ],
    )
    result = go(sc, tmp_path, capture="all", report=True)
    folder = tmp_path / "walk"
    assert {p.name for p in folder.glob("*.pcap")} == {
        "medium.pcap",
        "r1.pcap",
        "r2.pcap",
        "r3.pcap",
    }
    updates = result.checks[-1]
    assert updates.ok is True and updates.detail.startswith("0 Update datagrams")
    assert result.report is not None
    meta = result.report["meta"]
    assert meta["status"] == "passed" and [c["ok"] for c in meta["checks"]] == [True] * 5
    assert set(result.report["traffic"]["robots"]) == {"r1", "r2", "r3"}
    assert {"connectivity", "agreement", "bytes_per_robot"} <= set(result.report["plots"])
    saved = json.loads((folder / "run.json").read_text())
    assert saved["samples"] and saved["truth"]
    (folder / "report.json").unlink()
    assert cli.main(["report", str(folder)]) == 0
    rebuilt = json.loads((folder / "report.json").read_text())
    assert rebuilt["meta"]["checks"] == meta["checks"]


def test_a_failed_wait_names_the_robot_stops_and_keeps_the_pcaps(tmp_path: Path) -> None:
    pytest.importorskip("scapy")
    sc = Scenario(
        "fail",
        robots=3,
        beacon=BEACON,
        steps=[
            Start(),
            Wait(Lists(groups=[["r1", "r2"], ["r3"]]), within="1 beacon"),
            Kill("r1"),
        ],
    )
    result = go(sc, tmp_path, status="failed", capture="robots")
    (check,) = result.checks
    assert "r1 lists {r2, r3} but should list {r2}" in check.detail
    folder = tmp_path / "fail"
    records = pcap.read_run(folder)
    assert {r.capture for r in records} == {"r1", "r2", "r3"}
    assert not any(r.msg_type == "Byebye" for r in records)  # r1 was not killed... nor stopped
    assert (folder / "logs" / "r1.log").exists()


def test_a_collision_gives_two_robots_one_derived_address(tmp_path: Path) -> None:
    sc = Scenario(
        "macs",
        robots=3,
        beacon=BEACON,
        steps=[Collision(["r1", "r3"]), Start(), Sleep(0.1)],
    )
    go(sc, tmp_path, capture="robots")
    macs = {
        r: json.loads((tmp_path / "macs" / f"{r}.pcap.json").read_text())["mac"]
        for r in ("r1", "r2", "r3")
    }
    assert len({macs["r1"], macs["r2"], macs["r3"]}) == 3
    assert next(candidates(1, macs["r1"])) == next(candidates(1, macs["r3"]))


def test_shaping_this_kernel_cannot_do_is_a_step_error(tmp_path: Path) -> None:
    if capabilities().netem:
        pytest.skip("this kernel has netem: delay works")
    sc = Scenario("delay", robots=1, steps=[Shape("r1", {"delay": 50})])
    result = go(sc, tmp_path, status="error")
    assert result.error is not None and result.error.startswith("step 1 (shape): ")
    assert "sch_netem" in result.error


# -- fixtures ---------------------------------------------------------------------------------


def test_the_lab_fixture_gives_a_fresh_lab(lab: Lab) -> None:
    assert lab.is_up and not lab.robots and len(lab.name) <= 8
    lab.add_robots(["r1", "r2"])
    assert kernel.list_ns(naming.prefix(lab.name)) == sorted(
        [naming.air_ns(lab.name), naming.robot_ns(lab.name, "r1"), naming.robot_ns(lab.name, "r2")]
    )


def test_lab_teardown_tolerates_what_the_test_removed(lab: Lab) -> None:
    lab.add_robots(["r1", "r2"])
    kernel.remove_ns(naming.robot_ns(lab.name, "r2"))


def test_lab_teardown_tolerates_a_lab_already_down(lab_factory: Callable[..., Lab]) -> None:
    first, second = lab_factory(), lab_factory()
    assert first.name != second.name
    first.add_robot("r1")
    first.down()


def listed(lab: Lab, robot: str) -> set[str]:
    try:
        return {n["robot_id"] for n in lab.client(robot).neighbors()}
    except ApiError:
        return set()


def wait_for(pred: Callable[[], bool], timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.05)
    return pred()


@pytest.mark.fleet(n=2, beacon=0.5)
def test_the_fleet_marker_sets_robots_and_beacon(fleet: Lab) -> None:
    assert list(fleet.robots) == ["r1", "r2"] and fleet.alive("r1") and fleet.alive("r2")
    assert "--beacon-interval 0.5" in fleet.robot("r1").log.read_text()
    assert wait_for(lambda: listed(fleet, "r1") == {"r2"}, 2.0)


def test_fleet_factory_makes_fleets_on_demand(fleet_factory: Callable[..., Lab]) -> None:
    idle = fleet_factory(2, start=False)
    assert not idle.alive("r1")
    one = fleet_factory(1, beacon=0.5)
    assert one.alive("r1") and one.name != idle.name


# -- the command line -------------------------------------------------------------------------

TINY = """
[scenario]
name = "tiny"
robots = 2
beacon = 0.5

[[step]]
start = "all"

[[step]]
check = "lists"
{extra}
within = "2 s"
"""


def test_netlab_run_exits_by_the_checks(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("matplotlib")
    good, bad = tmp_path / "good.toml", tmp_path / "bad.toml"
    good.write_text(TINY.format(extra=""))
    bad.write_text(TINY.format(extra='groups = [["r1"], ["r2"]]').replace("2 s", "0.2 s"))
    runs = tmp_path / "runs"
    assert cli.main(["run", str(good), "--runs", str(runs), "--no-capture"]) == 0
    out = capsys.readouterr().out
    assert "ok    all running robots list each other" in out and "tiny: PASSED" in out
    assert cli.main(["run", str(bad), "--runs", str(runs), "--no-capture", "--no-report"]) == 1
    out = capsys.readouterr().out
    assert "r1 lists {r2} but should list {}" in out and "tiny: FAILED" in out
    assert len(list(runs.glob("tiny-*/report.json"))) == 1
    assert len(list(runs.glob("tiny-*/run.json"))) == 2
    assert list(runs.glob("tiny-*/*.png"))
    # --no-plots: the report without its PNGs, and the run says so.
    plain = tmp_path / "plain"
    assert cli.main(["run", str(good), "--runs", str(plain), "--no-capture", "--no-plots"]) == 0
    assert "(report.json; no plots;" in capsys.readouterr().out
    assert len(list(plain.glob("tiny-*/report.json"))) == 1
    assert not list(plain.glob("tiny-*/*.png"))


def test_netlab_capture_on_a_lab_brought_up(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("scapy")
    name = unique_lab_name()
    try:
        up = ["up", name, "--robots", "2", "--start", "--beacon-interval", "0.5"]
        assert cli.main(up) == 0
        out = tmp_path / "r1.pcap"
        assert cli.main(["capture", name, "r1", "--out", str(out), "--duration", "1.2"]) == 0
        air = tmp_path / "air.pcap"
        assert cli.main(["capture", name, "medium", "--out", str(air), "--duration", "1.2"]) == 0
        assert cli.main(["capture", name, "r9", "--out", str(air), "--duration", "1"]) == 1
        text = capsys.readouterr()
        assert "no robot 'r9'" in text.err and "frames captured" in text.out
        mine = list(pcap.read_pcap(out))
        assert {r.robot for r in mine if r.direction == "tx" and r.kind == "sdfr"} == {"r1"}
        assert {r.robot for r in pcap.read_pcap(air) if r.kind == "sdfr"} == {"r1", "r2"}
    finally:
        assert cli.main(["down", name, "--cleanup"]) == 0
