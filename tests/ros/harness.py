"""Driving ROS processes inside netlab robots: the node, and a probe speaking JSON lines."""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest

from netlab.lab import Lab

REPO = Path(__file__).resolve().parents[2]


def tail(path: Path, lines: int = 30) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no log)"


def ros2_environ(domain: int) -> dict[str, str]:
    """ROS 2 inside a robot: DDS on the robot's loopback only (its namespace: nothing leaks to
    the host or another robot), over UDP (Fast DDS's shared memory lives in /dev/shm, which
    namespaces share), on a domain of this robot alone."""
    env = dict(os.environ)
    env.update(
        ROS_DOMAIN_ID=str(domain),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        FASTDDS_BUILTIN_TRANSPORTS="UDPv4",
        PYTHONPATH=str(REPO),
        PYTHONUNBUFFERED="1",
    )
    env.pop("ROS_LOCALHOST_ONLY", None)
    return env


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


class Proc:
    """A process in a robot, its output in a log file; stopped by `stop()` (or the lab)."""

    def __init__(
        self, lab: Lab, robot: str, argv: list[str], env: dict[str, str], log: Path, **kw: Any
    ) -> None:
        self.log = log
        self.argv = argv
        with open(log, "ab") as out:
            kw.setdefault("stdout", out)
            self.proc = lab.popen(robot, argv, env=env, stderr=out, **kw)

    def stop(self, sig: int = signal.SIGINT, timeout: float = 20.0) -> int:
        """`sig` (a ROS node's Ctrl-C), then SIGKILL to its group after `timeout`."""
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.proc.pid, sig)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
                pytest.fail(f"{self.argv[:4]} did not stop within {timeout} s of signal {sig}")
        return self.proc.returncode


class Probe(Proc):
    """tests/ros/probe_ros{1,2}.py in a robot: `call(op, **args)` -> its JSON answer."""

    def __init__(self, lab: Lab, robot: str, python: Path, script: str, env: dict[str, str],
                 log: Path) -> None:  # fmt: skip
        super().__init__(
            lab, robot, [str(python), str(REPO / "tests" / "ros" / script)], env, log,
            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        )  # fmt: skip

    def call(self, op: str, timeout: float = 60.0, **args: Any) -> dict[str, Any]:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        try:
            self.proc.stdin.write(json.dumps({"op": op, **args}).encode() + b"\n")
            self.proc.stdin.flush()
        except BrokenPipeError:
            pytest.fail(f"the probe exited ({self.proc.poll()}); its log:\n{tail(self.log)}")
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout)
        line = self.proc.stdout.readline() if ready else b""
        if not line:
            pytest.fail(
                f"the probe did not answer {op} within {timeout} s; its log:\n{tail(self.log)}"
            )
        answer: dict[str, Any] = json.loads(line)
        if not answer["ok"]:
            pytest.fail(f"probe {op}{args}: {answer['error']}\n{answer.get('trace', '')}")
        return answer

    def close(self) -> None:
        if self.proc.stdin is not None:
            with contextlib.suppress(BrokenPipeError):
                self.proc.stdin.close()
        try:
            self.proc.wait(15)
        except subprocess.TimeoutExpired:
            self.stop(signal.SIGKILL)
        if self.proc.stdout is not None:
            self.proc.stdout.close()


def robot_ids(neighbor_list: dict[str, Any]) -> list[str]:
    return [r["robot_id"] for r in neighbor_list["robots"]]


def wait_until(what: str, cond: Any, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            pytest.fail(f"not within {timeout} s: {what}")
        time.sleep(0.1)
