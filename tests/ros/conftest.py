"""The ROS tiers: the `sdfr` node under real ROS 2 (rclpy, Fast DDS, from PyPI wheels in
.venv/ros2) and real ROS 1 (roscore and rospy from Debian's packages, .venv/ros1), each on
two netlab robots with a daemon of their own.

The environments are set up here when missing (scripts/ros2-setup.sh, scripts/ros1-setup.sh:
idempotent, a second or so when done already).  When a tier cannot run, its tests fail
saying why; SDFR_SKIP_ROS=1 skips both tiers and says so.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SKIP = os.environ.get("SDFR_SKIP_ROS") == "1"


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if not SKIP:
        return
    mark = pytest.mark.skip(reason="SDFR_SKIP_ROS=1: the ROS tiers are skipped")
    for item in items:
        if Path(str(item.fspath)).is_relative_to(Path(__file__).parent):
            item.add_marker(mark)


def _set_up(script: str) -> None:
    if os.geteuid() != 0:
        pytest.fail(f"the ROS tiers need root (set SDFR_SKIP_ROS=1 to skip them); {script} not run")
    res = subprocess.run(
        ["bash", f"scripts/{script}"], cwd=REPO, capture_output=True, text=True, timeout=1200,
        stdin=subprocess.DEVNULL,
    )  # fmt: skip
    if res.returncode != 0:
        pytest.fail(
            f"scripts/{script} failed, so this ROS tier cannot run:\n{res.stdout}{res.stderr}"
        )


@pytest.fixture(scope="session")
def ros2_env() -> Path:
    """The ROS 2 interpreter (.venv/ros2/bin/python), set up."""
    _set_up("ros2-setup.sh")
    return REPO / ".venv" / "ros2" / "bin" / "python"


@pytest.fixture(scope="session")
def ros1_env() -> Path:
    """The ROS 1 interpreter (.venv/ros1/bin/python), set up."""
    _set_up("ros1-setup.sh")
    return REPO / ".venv" / "ros1" / "bin" / "python"
