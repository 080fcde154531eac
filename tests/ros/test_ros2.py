"""The ROS 2 tier: the `sdfr` node under real rclpy and Fast DDS, on two netlab robots.

r1 runs sdfrd (started by netlab) and a node that finds it; r2 runs only a node, which starts
r2's sdfrd itself.  A probe on each robot (tests/ros/probe_ros2.py) is a ROS 2 program using
the node: a service published through ~/publish on r1 appears in ~/neighbors and ~/changes on
r2 and is found by ~/search; unpublished, it goes again.  DDS stays inside each robot.
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path
from typing import Any

import pytest

from netlab.lab import Lab
from sdfr.testing.ros import Probe, Proc, ros2_environ, tail
from tests.ros.harness import PROBES, REPO, robot_ids

pytestmark = pytest.mark.root

PARAMS_FILE = REPO / "ros" / "sdfr_ros" / "config" / "sdfr.params.yaml"
BEACON = 0.5
CAMERA: dict[str, Any] = {
    "name": "front camera",
    "type": "sensor.camera",
    "url": "rtsp://r1/front",
    "attributes": [["fps", 30], ["hd", True], ["lens", "wide"], ["fov", 1.5]],
}


def node_argv(python: Path, *params: str) -> list[str]:
    argv = [str(python), "-m", "sdfr.ros.ros2", "--ros-args", "--params-file", str(PARAMS_FILE)]
    for p in params:
        argv += ["-p", p]
    return argv


def domains() -> tuple[int, int]:
    base = 2 * (os.getpid() % 50)  # this run's, so that two runs differ too
    return base, base + 1


def test_a_service_published_on_one_robot_is_seen_and_found_on_the_other(
    lab: Lab, ros2_env: Path, tmp_path: Path
) -> None:
    lab.add_robot("r1", pos=(0.0, 0.0))
    r2 = lab.add_robot("r2", pos=(1.0, 0.0))
    # Apart until both probes listen (run_flow merges): r2's node tells r1's arrival on
    # ~/changes, which keeps nothing for a late subscriber; CI saw r2's sdfrd, started by
    # its node, list r1 before probe 2 subscribed.
    lab.partition([["r1"], ["r2"]])
    lab.start("r1", beacon_interval=BEACON)
    d1, d2 = domains()
    env1, env2 = ros2_environ(d1), ros2_environ(d2)
    node1 = Proc(lab, "r1", node_argv(ros2_env, "poll_interval:=0.1"), env1, tmp_path / "node1.log")
    spawn_args = f"--iface eth0 --robot-id r2 --state-dir {r2.state_dir} --beacon-interval {BEACON}"
    node2 = Proc(
        lab, "r2",
        node_argv(ros2_env, f"fleet:={lab.fleet}", f"sdfrd_args:={spawn_args}",
                  f"sdfrd_log:={tmp_path / 'sdfrd-r2.log'}", "poll_interval:=0.1"),
        env2, tmp_path / "node2.log",
    )  # fmt: skip
    p1 = Probe(lab, "r1", ros2_env, PROBES / "probe_ros2.py", env1, tmp_path / "probe1.log")
    p2 = Probe(lab, "r2", ros2_env, PROBES / "probe_ros2.py", env2, tmp_path / "probe2.log")
    try:
        run_flow(lab, p1, p2, node1, node2, tmp_path)
    except BaseException:
        for name in ("node1.log", "node2.log", "sdfrd-r2.log", "probe1.log", "probe2.log"):
            print(f"--- {name}:\n{tail(tmp_path / name)}")
        raise
    finally:
        p1.close()
        p2.close()
        node1.stop()
        node2.stop()


def run_flow(lab: Lab, p1: Probe, p2: Probe, node1: Proc, node2: Proc, tmp: Path) -> None:
    # Both nodes up; each probe got the latched list (it subscribed after it was published).
    first = p1.call("ready")["neighbors"]
    assert first["robot_id"] == "r1"
    assert p2.call("ready")["neighbors"]["robot_id"] == "r2"
    lab.merge()
    p2.call("wait_neighbors", robot="r1")
    p1.call("wait_neighbors", robot="r2")

    # r1 publishes through ~/publish; r2 sees it on ~/neighbors, typed as it was sent.
    sent = p1.call("publish", service=CAMERA)["t"]
    seen = p2.call("wait_neighbors", robot="r1", name="front camera", since=sent)
    (r1,) = [r for r in seen["msg"]["robots"] if r["robot_id"] == "r1"]
    (cam,) = r1["services"]
    assert (cam["name"], cam["type"], cam["url"]) == (
        "front camera",
        "sensor.camera",
        "rtsp://r1/front",
    )
    attrs = {a["key"]: a for a in cam["attributes"]}
    assert (attrs["fps"]["type"], attrs["fps"]["integer_value"]) == (1, 30)
    assert (attrs["hd"]["type"], attrs["hd"]["bool_value"]) == (3, True)
    assert (attrs["lens"]["type"], attrs["lens"]["string_value"]) == (0, "wide")
    assert (attrs["fov"]["type"], attrs["fov"]["double_value"]) == (2, 1.5)
    assert r1["reachable"] is True and r1["address"] == lab.robot("r1").ip
    assert seen["msg"]["robot_id"] == "r2" and seen["msg"]["stamp"] > 0

    # ~/search on r2 finds it by type and attributes, and only with the right values.
    found = p2.call("search", type="sensor.camera", attributes=[["fps", 30], ["hd", True]])
    assert found["response"]["success"] is True
    assert robot_ids(found["response"]) == ["r1"]
    assert found["response"]["robots"][0]["services"][0]["id"] == cam["id"]
    none = p2.call("search", type="sensor.camera", attributes=[["fps", 15]])["response"]
    assert none["success"] is True and none["robots"] == []
    bad = p2.call("search", type="", attributes=[])["response"]
    assert bad["success"] is False and "give a type or at least one attribute" in bad["message"]

    # ~/list on r1: its own service; its neighbour r2.
    listing = p1.call("list")["response"]
    assert listing["robot_id"] == "r1" and [s["name"] for s in listing["services"]] == [
        "front camera"
    ]
    assert robot_ids(listing) == ["r2"]

    # ~/changes on r2: r1 arrived, then its service.
    kinds = [
        (c["kind"], c["robot_id"], c["service"]["name"]) for c in p2.call("changes")["changes"]
    ]
    assert (1, "r1", "") in kinds and (4, "r1", "front camera") in kinds

    # A bad message is refused with an error naming what was wrong (the node's log).
    p1.call("publish", service={"name": "x", "type": "t",
                                "attributes": [{"key": "k", "type": 9}]})  # fmt: skip
    # Unpublished on r1 (the same message: its id is derived from type and name), gone on r2.
    sent = p1.call("unpublish", service=CAMERA)["t"]
    p2.call("wait_neighbors", robot="r1", name="front camera", present=False, since=sent)
    removed = [c for c in p2.call("changes")["changes"] if c["kind"] == 5]
    assert [c["service"]["name"] for c in removed] == ["front camera"]
    assert "attribute 'k': type 9 is not one of STRING(0), INTEGER(1), DOUBLE(2), BOOL(3)" in (
        (tmp / "node1.log").read_text()
    )

    # /diagnostics: the daemon's health; r2's node started its daemon, r1's did not.
    for probe, started in ((p1, "no"), (p2, "yes")):
        status = probe.call("diagnostics")["msg"]["status"][0]
        values = {kv["key"]: kv["value"] for kv in status["values"]}
        assert status["name"] == "sdfr: sdfrd" and status["level"] in (0, 1), status
        assert values["started_by_node"] == started and values["discovery"] == "up"

    # Stopping r2's node stops the sdfrd it started (r1 hears its Byebye); stopping r1's
    # leaves r1's daemon, which netlab started, running.
    left = time.time()
    assert node2.stop(signal.SIGINT) == 0
    p1.call("wait_neighbors", robot="r2", present=False, since=left, timeout=20)
    assert node1.stop(signal.SIGINT) == 0
    assert lab.alive("r1")
