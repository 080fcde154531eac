"""The ROS tests' side of driving ROS in netlab robots: ROS 1's environment, the probes'
scripts, and waiting (the node and the probes are run by `sdfr.testing.ros`)."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[2]
#: The probes' scripts (`sdfr.testing.ros.Probe` runs them): probe_ros1.py, probe_ros2.py.
PROBES = Path(__file__).resolve().parent


def ros1_environ(home: Path, port: int = 11311) -> dict[str, str]:
    """ROS 1 inside a robot: its own master on the robot's loopback."""
    env = dict(os.environ)
    env.update(
        ROS_MASTER_URI=f"http://127.0.0.1:{port}",
        ROS_IP="127.0.0.1",
        ROS_HOME=str(home),
        ROS_LOG_DIR=str(home / "log"),
        ROS_PACKAGE_PATH=f"{REPO / 'ros'}:/usr/share",
        PYTHONPATH=f"{REPO}:{REPO / '.venv' / 'ros1' / 'msgs'}",
        PYTHONUNBUFFERED="1",
    )
    return env


def robot_ids(neighbor_list: dict[str, Any]) -> list[str]:
    return [r["robot_id"] for r in neighbor_list["robots"]]


def wait_until(what: str, cond: Any, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            pytest.fail(f"not within {timeout} s: {what}")
        time.sleep(0.1)
