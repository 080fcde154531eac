"""The `netlab` command without a lab: its parser, help, did-you-mean, exec's words, logs from a
kept folder, the status table and pingall's verdicts."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from netlab import cli, labcli, pingall, scenario
from netlab.errors import NetlabError
from netlab.manifest import Manifest, RobotRecord
from netlab.pingall import Ping
from netlab.ranges import Topology, UnitDisc
from netlab.status import format_status, medium_state


def _subparsers(p: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in p._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def test_every_argument_of_every_action_has_help() -> None:
    actions = _subparsers(cli.build_parser())
    assert {"logs", "pingall", "exec", "down", "partition", "merge", "report"} <= set(actions)
    missing = [
        f"{name} {a.dest}"
        for name, p in actions.items()
        for a in p._actions
        if not a.help or a.help == argparse.SUPPRESS
    ]
    assert not missing, f"arguments without help: {missing}"
    assert set(cli.COMMANDS) == set(actions)


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["stauts"], "netlab: unknown command 'stauts' (did you mean 'status'?)"),
        (["pingal", "x"], "(did you mean 'pingall'?)"),
        (["down", "lab1", "--clenaup"], "unknown option --clenaup (did you mean '--cleanup'?)"),
        (["up", "lab1", "--robts", "3"], "netlab up: unknown option --robts (did you mean"),
        (["up", "lab1", "--robots", "2", "--runtime", "dokcer"], "(did you mean 'docker'?)"),
    ],
)
def test_a_mistyped_action_or_flag_gets_one_line_with_the_closest_spelling(
    capsys: pytest.CaptureFixture[str], argv: list[str], expected: str
) -> None:
    with pytest.raises(SystemExit) as exit_:
        cli.main(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert expected in err
    assert err.count("\n") == 1, err


def test_a_typo_in_a_topology_or_scenario_file_gets_the_closest_key(tmp_path: Path) -> None:
    topo = tmp_path / "t.toml"
    topo.write_text('[scenario]\nrobots = 3\nradious = 10\n[[step]]\nparttion = ["r1"]\n')
    with pytest.raises(scenario.ScenarioError, match=r"radious \(did you mean 'radius'\?\)"):
        scenario.load(topo)
    topo.write_text('[scenario]\nrobots = 3\n[[step]]\nparttion = ["r1"]\n')
    with pytest.raises(scenario.ScenarioError, match=r"no action \(did you mean 'partition'\?\)"):
        scenario.load(topo)
    topo.write_text('[scenario]\nrobots = 3\n[[step]]\ncheck = "agreemnt"\n')
    with pytest.raises(scenario.ScenarioError, match="did you mean 'agreement'"):
        scenario.load(topo)
    with pytest.raises(scenario.ScenarioError, match="did you mean 'mobility'"):
        scenario.find("mobilty")


def test_up_reads_a_topology_file_with_its_mistake_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    topo = tmp_path / "t.toml"
    topo.write_text("[scenario]\nrobots = 3\nradious = 10\n")
    assert cli.main(["up", "lab1", "-t", str(topo)]) == 1
    err = capsys.readouterr().err
    assert "did you mean 'radius'" in err and "Error" not in err


def test_exec_takes_a_robot_or_all_and_a_command_after_the_double_dash() -> None:
    def words(*argv: str) -> tuple[str | None, list[str]]:
        args = cli.build_parser().parse_args(["exec", *argv])
        return labcli.split_exec(list(args.cmd), args.all)

    assert words("lab", "r1", "--", "ip", "-br", "a") == ("r1", ["ip", "-br", "a"])
    assert words("lab", "r1", "ip", "-br", "a") == ("r1", ["ip", "-br", "a"])
    assert words("--all", "lab", "--", "hostname") == (None, ["hostname"])
    assert words("lab", "--all", "--", "hostname") == (None, ["hostname"])
    with pytest.raises(NetlabError, match="no command given after the robot 'r1'"):
        words("lab", "r1")
    with pytest.raises(NetlabError, match="no command given after the robot 'ls'"):
        words("lab", "--", "ls")  # (argparse drops a -- that comes first)
    with pytest.raises(NetlabError, match="name a robot, or --all"):
        labcli.split_exec(["--", "ls"], False)
    assert [labcli.exit_status(c) for c in (0, 3, -9)] == [0, 3, 137]


def test_logs_reads_a_kept_folder_and_names_the_robots_it_has(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "r1").mkdir()
    (tmp_path / "r1" / "sdfrd.log").write_text("one\ntwo\nthree\n")
    assert cli.main(["logs", str(tmp_path), "r1", "-n", "2"]) == 0
    assert capsys.readouterr().out == "two\nthree\n"
    assert cli.main(["logs", str(tmp_path), "r2"]) == 1
    assert "no daemon log" in capsys.readouterr().err
    assert cli.main(["logs", str(tmp_path), "r"]) == 1
    assert "(did you mean 'r1'?)" in capsys.readouterr().err


def _record(medium: bool) -> Manifest:
    record = Manifest("lab1", workdir="/tmp/netlab-lab1-x", detached=True)
    for i, name in enumerate(("r1", "r2", "r3")):
        record.robots[name] = RobotRecord(i, f"nl-lab1-{name}", f"v{name}", f"02:00:00:00:00:0{i}",
                                          f"10.1.0.{i + 1}/16")  # fmt: skip
    if medium:
        topo = Topology(UnitDisc(50.0))
        for name in record.robots:
            topo.add(name)
        topo.partition([["r1", "r2"]])
        topo.set_pair_quality("r1", "r2", 30.0, both=False)
        data = topo.to_json()
        assert data is not None
        record.medium = {**data, "shapes": {"r2": {"loss": 10.0, "delay": 20.0, "rate": None}}}
    return record


def _status(record: Manifest, sdfrd: int | None) -> dict[str, object]:
    return {
        "name": record.name,
        "runner": {"pid": 42, "alive": False, "detached": True},
        "workdir": record.workdir,
        "medium": True,
        "medium_state": medium_state(record),
        "robots": {n: _robot(r.address, r.mac, sdfrd) for n, r in record.robots.items()},
    }


def _robot(address: str, mac: str, sdfrd: int | None) -> dict[str, object]:
    return {"runtime": "namespace", "namespace": "ns", "present": True, "address": address,
            "mac": mac, "sdfrd": sdfrd}  # fmt: skip


def test_status_has_column_headers_and_the_medium_in_effect() -> None:
    text = format_status([_status(_record(medium=True), sdfrd=None)], {})
    lines = text.splitlines()
    assert lines[0] == "lab lab1: 3 robots, left up (netlab up)"
    assert "folder: /tmp/netlab-lab1-x" in lines[1]
    assert lines[2] == "medium: partition r1,r2 | r3; range 50 m; 2 of 6 directed links up"
    assert lines[3] == "  pair r1->r2: loss 30%"
    header = lines[4].split()
    assert header == ["ROBOT", "ADDRESS", "MAC", "KIND", "NETNS", "SDFRD", "HEARS", "SHAPE"]
    r2 = lines[6]
    assert r2.split()[:7] == ["r2", "10.1.0.2/16", "02:00:00:00:00:01", "namespace", "ok",
                              "stopped", "1"]  # fmt: skip
    assert r2.endswith("loss 10%, delay 20ms")
    assert lines[7].split()[6] == "0"  # r3, alone in its group, hears no one
    # The columns line up under their headers.
    assert lines[6].index("stopped") == lines[4].index("SDFRD")


def test_status_of_a_lab_whose_runner_keeps_the_medium_says_so() -> None:
    text = format_status([_status(_record(medium=False), sdfrd=1234)], {})
    assert "medium: kept by its runner (pid 42)" in text
    assert "pid 1234" in text and "no partition" not in text
    assert format_status([], {}).startswith("no labs")
    merged = _record(medium=True)
    merged.medium["groups"] = None
    assert "medium: no partition;" in format_status([_status(merged, None)], {})


def test_pingall_parses_ping_and_fails_only_a_linked_pair_without_reply() -> None:
    out = "3 packets transmitted, 2 received, 33.3333% packet loss, time 402ms"
    assert pingall.parse_ping(out) == Ping(3, 2)
    assert pingall.parse_ping("ping: connect: Network is unreachable").sent == 0
    both = {("a", "b"): 0.0, ("b", "a"): 0.0}
    results = {
        ("a", "b"): Ping(3, 3),
        ("b", "a"): Ping(3, 2),
        ("a", "c"): Ping(3, 0),
        ("c", "a"): Ping(3, 0),
        ("b", "c"): Ping(3, 0),
        ("c", "b"): Ping(3, 1),
    }
    verdict = pingall.judge(results, both)
    assert verdict.ok and verdict.unexpected == [("c", "b")]
    assert (verdict.sent, verdict.received) == (6, 5)
    rows = pingall.matrix(["a", "b", "c"], results, both)
    assert rows[0].split() == ["from\\to", "a", "b", "c"]
    assert rows[1].split() == ["a", "-", "0%", "cut"]
    assert rows[3].split() == ["c", "cut", "ANSWERS", "67%", "-"]
    assert "16.7% dropped (5/6 received" in pingall.summary(verdict)
    everyone = pingall.judge(results, None)
    assert not everyone.ok and ("a", "c") in everyone.failed
