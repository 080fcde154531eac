"""sdfrd's supervisor with real layers on the loopback interface: a layer that cannot start
ends sdfrd at once, a stopped (SIGSTOP) layer is restarted, and systemd's notify protocol
(READY, WATCHDOG, STOPPING) arrives on a real unix datagram socket."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from sdfr.api import HEARTBEAT_STALE
from sdfr.client import Client
from sdfr.daemon.supervisor import EXIT_CANNOT_START, STALL_AFTER
from tests.support.api import free_port
from tests.support.waiting import poll

pytestmark = pytest.mark.root  # SO_BINDTODEVICE on lo


def sdfrd_argv(state: Path, *extra: str) -> list[str]:
    return [
        sys.executable, "-m", "sdfr.daemon.supervisor", "--iface", "lo", "--robot-id", "t1",
        "--state-dir", str(state), "--api", f"127.0.0.1:{free_port()}",
        "--describe", f"127.0.0.1:{free_port()}", "--port", str(free_port()),
        "--beacon-interval", "1", *extra,
    ]  # fmt: skip


class Daemon:
    def __init__(self, tmp: Path, env: dict[str, str] | None = None, *extra: str) -> None:
        self.state = tmp / "state"
        self.argv = sdfrd_argv(self.state, *extra)
        self.api = self.argv[self.argv.index("--api") + 1]
        self.log = tmp / "sdfrd.log"
        with self.log.open("ab") as out:
            self.proc = subprocess.Popen(
                self.argv, stdout=out, stderr=subprocess.STDOUT, env={**os.environ, **(env or {})}
            )

    def layers(self) -> dict[str, int]:
        try:
            return dict(json.loads((self.state / "layers.json").read_text()))
        except (OSError, ValueError):
            return {}

    def health(self) -> str:
        with Client(self.api, timeout=1.0) as c:
            try:
                return str(c.health()["discovery"])
            except Exception as exc:
                return f"no answer: {exc}"

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode

    def text(self) -> str:
        return self.log.read_text(errors="replace")


@pytest.fixture
def daemons(tmp_path: Path) -> Iterator[list[Daemon]]:
    made: list[Daemon] = []
    yield made
    for d in made:
        d.stop()


def test_a_layer_that_cannot_start_ends_sdfrd_at_once(
    tmp_path: Path, daemons: list[Daemon]
) -> None:
    # 192.0.2.1 (TEST-NET-1) is no address of this machine: binding it cannot work.
    argv = sdfrd_argv(tmp_path / "s2")
    argv[argv.index("--api") + 1] = "192.0.2.1:8700"
    started = time.monotonic()
    res = subprocess.run(argv, capture_output=True, text=True, timeout=30)
    took = time.monotonic() - started
    assert res.returncode == EXIT_CANNOT_START, res.stderr
    assert "--api 192.0.2.1:8700: cannot listen" in res.stderr
    assert "cannot assign requested address" in res.stderr
    assert "a restart would not fix it" in res.stderr
    assert took < 10, f"took {took:.1f} s"
    assert "restarting in" not in res.stderr


def test_a_stopped_discovery_layer_is_restarted(tmp_path: Path, daemons: list[Daemon]) -> None:
    d = Daemon(tmp_path)
    daemons.append(d)
    poll("discovery up", lambda: d.health() == "up" or d.health(), 20.0)
    old = d.layers()["discovery"]
    os.kill(old, signal.SIGSTOP)
    try:
        # /health says down after HEARTBEAT_STALE; the supervisor acts after STALL_AFTER.
        poll("discovery down", lambda: d.health() == "down" or d.health(), 10.0)
        stopped_at = time.monotonic()
        poll(
            "a new discovery layer",
            lambda: d.layers().get("discovery", old) != old or f"layers {d.layers()}",
            STALL_AFTER + 10,
        )
        # Not before it was due (stopped_at is HEARTBEAT_STALE or more after the stop).
        assert time.monotonic() - stopped_at >= STALL_AFTER - HEARTBEAT_STALE - 1
        poll("discovery up again", lambda: d.health() == "up" or d.health(), 20.0)
    finally:
        if os.path.exists(f"/proc/{old}"):
            os.kill(old, signal.SIGKILL)
    assert "has not beaten for" in d.text() and "hung or stopped" in d.text()
    assert d.stop() == 0


class NotifySocket:
    """What a service manager listens on: a unix datagram socket."""

    def __init__(self, path: str) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(path)
        self.sock.settimeout(0.2)
        self.got: list[str] = []

    def until(self, line: str, timeout: float) -> float:
        start = time.monotonic()
        while time.monotonic() - start < timeout:
            with contextlib.suppress(TimeoutError):
                self.got += self.sock.recv(4096).decode().split("\n")
            if line in self.got:
                return time.monotonic() - start
        raise AssertionError(f"no {line!r} within {timeout} s; got {self.got}")


def test_systemd_notify_ready_watchdog_stopping(tmp_path: Path, daemons: list[Daemon]) -> None:
    path = str(tmp_path / "notify.sock")
    manager = NotifySocket(path)
    # WATCHDOG_PID names the process systemd watches: the supervisor (Popen's pid).
    env = {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "1000000"}
    d = Daemon(tmp_path, env)
    daemons.append(d)
    manager.until("READY=1", 30)
    assert any(x.startswith("STATUS=serving the API on") for x in manager.got)
    assert d.health() == "up"  # READY=1 only once both layers beat
    manager.got.clear()
    manager.until("WATCHDOG=1", 2.0)
    manager.got.clear()
    manager.until("WATCHDOG=1", 1.0)  # every half interval
    d.proc.terminate()
    manager.until("STOPPING=1", 10)
    assert d.stop() == 0
    # The layers never got the manager's variables (only the supervisor speaks to it).
    assert "cannot notify systemd" not in d.text()
