"""Driving ROS processes inside netlab robots: the node, and a probe speaking JSON lines.

A robot is reached through anything with netlab's `Lab.popen` (`Robots`), so this module
imports neither netlab nor ROS. A probe (the ROS tests' `tests/ros/probe_ros{1,2}.py`) reads
one JSON request a line on stdin and answers one JSON line on stdout: ``{"ok": true, ...}``
or ``{"ok": false, "error": ..., "trace": ...}``. What goes wrong raises `ProbeFailed`.
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import subprocess
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Protocol

#: The directory that holds the sdfr package (a checkout's root): what a ROS environment puts
#: on its PYTHONPATH to import this sdfr.
SOURCE_ROOT = Path(__file__).resolve().parents[2]


class Robots(Protocol):
    """What starts a process inside a robot (netlab's `Lab`)."""

    def popen(self, ref: str, argv: Sequence[str], **kw: Any) -> subprocess.Popen[Any]: ...


class ProbeFailed(AssertionError):
    """A process in a robot did not do what was asked of it (a test fails with this)."""


def tail(path: Path, lines: int = 30) -> str:
    """The last `lines` lines of a log file, for a failure's message."""
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
        PYTHONPATH=str(SOURCE_ROOT),
        PYTHONUNBUFFERED="1",
    )
    env.pop("ROS_LOCALHOST_ONLY", None)
    return env


class Proc:
    """A process in a robot, its output in a log file; stopped by `stop()` (or the lab)."""

    def __init__(
        self, lab: Robots, robot: str, argv: list[str], env: dict[str, str], log: Path, **kw: Any
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
                raise ProbeFailed(
                    f"{self.argv[:4]} did not stop within {timeout} s of signal {sig}"
                ) from None
        returncode: int = self.proc.returncode
        return returncode


class Probe(Proc):
    """The probe `script` run by `python` in a robot: `call(op, **args)` -> its JSON answer."""

    def __init__(self, lab: Robots, robot: str, python: Path, script: Path, env: dict[str, str],
                 log: Path) -> None:  # fmt: skip
        super().__init__(
            lab, robot, [str(python), str(script)], env, log,
            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        )  # fmt: skip

    def call(self, op: str, timeout: float = 60.0, **args: Any) -> dict[str, Any]:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        try:
            self.proc.stdin.write(json.dumps({"op": op, **args}).encode() + b"\n")
            self.proc.stdin.flush()
        except BrokenPipeError:
            raise ProbeFailed(
                f"the probe exited ({self.proc.poll()}); its log:\n{tail(self.log)}"
            ) from None
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout)
        line = self.proc.stdout.readline() if ready else b""
        if not line:
            raise ProbeFailed(
                f"the probe did not answer {op} within {timeout} s; its log:\n{tail(self.log)}"
            )
        answer: dict[str, Any] = json.loads(line)
        if not answer["ok"]:
            raise ProbeFailed(f"probe {op}{args}: {answer['error']}\n{answer.get('trace', '')}")
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
