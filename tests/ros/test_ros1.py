"""The ROS 1 tier: the `sdfr` node under a real roscore and rospy (Debian's packages), on two
netlab robots, each with its own master on its own loopback.

r1 runs sdfrd (started by netlab) and the node run directly; r2's node is started by
`roslaunch sdfr_ros sdfr.launch` and starts r2's sdfrd itself.  Probes (probe_ros1.py) use
the node as a rospy program would, and the command-line tools as the README shows them.
"""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path
from typing import Any

import pytest

from netlab.lab import Lab
from sdfr.testing.ros import Probe, Proc, tail
from tests.ros.harness import PROBES, robot_ids, ros1_environ, wait_until

pytestmark = pytest.mark.root

BEACON = 0.5
CAMERA: dict[str, Any] = {
    "name": "front camera",
    "type": "sensor.camera",
    "url": "rtsp://r1/front",
    "attributes": [["fps", 30], ["hd", True], ["lens", "wide"], ["fov", 1.5]],
}
LOGS = ("roscore1.log", "roscore2.log", "node1.log", "node2.log", "sdfrd-r2.log",
        "probe1.log", "probe2.log")  # fmt: skip


def master_up(lab: Lab, robot: str, env: dict[str, str]) -> bool:
    res = lab.exec(robot, ["rosnode", "list"], env=env, timeout=20)
    return res.returncode == 0 and "/rosout" in res.stdout


def test_the_same_flow_through_rospy_roslaunch_and_the_command_line(
    lab: Lab, ros1_env: Path, tmp_path: Path
) -> None:
    lab.add_robot("r1", pos=(0.0, 0.0))
    r2 = lab.add_robot("r2", pos=(1.0, 0.0))
    # Apart until both probes listen (run_flow merges): r2's node tells r1's arrival on
    # ~/changes, which keeps nothing for a late subscriber (as in test_ros2).
    lab.partition([["r1"], ["r2"]])
    lab.start("r1", beacon_interval=BEACON)
    env1 = ros1_environ(tmp_path / "ros-r1")
    env2 = ros1_environ(tmp_path / "ros-r2")
    procs: list[Proc] = []
    probes: list[Probe] = []
    try:
        for robot, env, log in (("r1", env1, "roscore1.log"), ("r2", env2, "roscore2.log")):
            procs.append(Proc(lab, robot, ["roscore", "-p", "11311"], env, tmp_path / log))
        for robot, env in (("r1", env1), ("r2", env2)):
            wait_until(f"roscore on {robot}", lambda r=robot, e=env: master_up(lab, r, e), 60)
        node1 = Proc(
            lab, "r1", [str(ros1_env), "-m", "sdfr.ros.ros1", "_poll_interval:=0.1"], env1,
            tmp_path / "node1.log",
        )  # fmt: skip
        procs.append(node1)
        spawn_args = (
            f"--iface eth0 --robot-id r2 --state-dir {r2.state_dir} --beacon-interval {BEACON}"
        )
        node2 = Proc(
            lab, "r2",
            ["roslaunch", "--wait", "sdfr_ros", "sdfr.launch", f"fleet:={lab.fleet}",
             f"sdfrd_args:={spawn_args}", f"sdfrd_log:={tmp_path / 'sdfrd-r2.log'}",
             "poll_interval:=0.1"],
            env2, tmp_path / "node2.log",
        )  # fmt: skip
        procs.append(node2)
        probes += [
            Probe(lab, "r1", ros1_env, PROBES / "probe_ros1.py", env1, tmp_path / "probe1.log"),
            Probe(lab, "r2", ros1_env, PROBES / "probe_ros1.py", env2, tmp_path / "probe2.log"),
        ]
        run_flow(lab, *probes, env1, env2, node1, node2, tmp_path)
    except BaseException:
        for name in LOGS:
            print(f"--- {name}:\n{tail(tmp_path / name)}")
        raise
    finally:
        for probe in probes:
            probe.close()
        for proc in reversed(procs):
            proc.stop()


def run_flow(
    lab: Lab, p1: Probe, p2: Probe, env1: dict[str, str], env2: dict[str, str],
    node1: Proc, node2: Proc, tmp: Path,
) -> None:  # fmt: skip
    assert p1.call("ready")["neighbors"]["robot_id"] == "r1"
    assert p2.call("ready")["neighbors"]["robot_id"] == "r2"  # latched: sent before we came
    lab.merge()
    p2.call("wait_neighbors", robot="r1")

    # rospy: publish on r1, seen on r2 typed as sent, found by ~search.
    sent = p1.call("publish", service=CAMERA)["t"]
    seen = p2.call("wait_neighbors", robot="r1", name="front camera", since=sent)
    (r1,) = [r for r in seen["msg"]["robots"] if r["robot_id"] == "r1"]
    attrs = {a["key"]: a for a in r1["services"][0]["attributes"]}
    assert (attrs["fps"]["type"], attrs["fps"]["integer_value"]) == (1, 30)
    assert (attrs["hd"]["type"], attrs["hd"]["bool_value"]) == (3, True)
    assert (attrs["fov"]["type"], attrs["fov"]["double_value"]) == (2, 1.5)
    assert r1["address"] == lab.robot("r1").ip and seen["msg"]["stamp"] > 0
    found = p2.call("search", type="sensor.camera", attributes=[["fps", 30]])["response"]
    assert found["success"] is True and robot_ids(found) == ["r1"]
    listing = p1.call("list")["response"]
    assert [s["name"] for s in listing["services"]] == ["front camera"]
    kinds = [(c["kind"], c["robot_id"]) for c in p2.call("changes")["changes"]]
    assert (1, "r1") in kinds and (4, "r1") in kinds

    # The command line, as the README shows it: rostopic echo and rosservice call on r2.
    echo = lab.exec("r2", ["rostopic", "echo", "-n", "1", "/sdfr/neighbors"], env=env2, timeout=30)
    assert echo.returncode == 0, echo.stderr
    assert 'robot_id: "r1"' in echo.stdout and 'name: "front camera"' in echo.stdout, echo.stdout
    call = lab.exec(
        "r2",
        ["rosservice", "call", "/sdfr/search",
         "{type: 'sensor.camera', attributes: [{key: 'fps', type: 1, integer_value: 30}]}"],
        env=env2, timeout=30,
    )  # fmt: skip
    assert call.returncode == 0, call.stderr
    assert "success: True" in call.stdout and 'robot_id: "r1"' in call.stdout, call.stdout
    # ... and rostopic pub on r1: a service with no attributes, seen by rospy on r2.
    sent = time.time()
    pub = lab.exec(
        "r1",
        ["rostopic", "pub", "-1", "/sdfr/publish", "sdfr_msgs/Service",
         "{name: 'map', type: 'map.server', url: 'http://r1/map'}"],
        env=env1, timeout=30,
    )  # fmt: skip
    assert pub.returncode == 0, pub.stderr
    p2.call("wait_neighbors", robot="r1", name="map", since=sent)

    # Unpublish on r1, gone on r2; /diagnostics on both.
    sent = p1.call("unpublish", service=CAMERA)["t"]
    p2.call("wait_neighbors", robot="r1", name="front camera", present=False, since=sent)
    for probe, started in ((p1, "no"), (p2, "yes")):
        status = probe.call("diagnostics")["msg"]["status"][0]
        values = {kv["key"]: kv["value"] for kv in status["values"]}
        # (The whole status on failure: its values say the discovery heartbeat's age.)
        assert status["name"] == "sdfr: sdfrd" and status["level"] in (0, 1), json.dumps(status)
        assert values["started_by_node"] == started and values["discovery"] == "up"

    # roslaunch stops its node on Ctrl-C, and the node the sdfrd it started (r1 hears its
    # Byebye); r1's node leaves r1's daemon, which it did not start, running.
    left = time.time()
    assert node2.stop(signal.SIGINT) == 0
    p1.call("wait_neighbors", robot="r2", present=False, since=left, timeout=20)
    assert node1.stop(signal.SIGINT) == 0
    assert lab.alive("r1")
    assert "started it:" in (tmp / "node2.log").read_text()
