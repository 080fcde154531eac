"""sdfrd's supervisor with real layers on the loopback interface: a layer that cannot start
ends sdfrd at once, a stopped (SIGSTOP) layer is restarted, and systemd's notify protocol
(READY, WATCHDOG, STOPPING) arrives on a real unix datagram socket. With `--layers threads`
the layers are threads of one process: a layer that fails is restarted alone while the other
serves, and a hung one restarts the whole daemon in the same process."""

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
from sdfr.daemon.supervisor import CHECK_EVERY, EXIT_CANNOT_START, STALL_AFTER
from tests.support.api import free_port
from tests.support.waiting import poll

pytestmark = pytest.mark.root  # SO_BINDTODEVICE on lo


def sdfrd_argv(state: Path, *extra: str, program: tuple[str, ...] = ()) -> list[str]:
    return [
        sys.executable, *(program or ("-m", "sdfr.daemon.supervisor")), "--iface", "lo",
        "--robot-id", "t1",
        "--state-dir", str(state), "--api", f"127.0.0.1:{free_port()}",
        "--describe", f"127.0.0.1:{free_port()}", "--port", str(free_port()),
        "--beacon-interval", "1", *extra,
    ]  # fmt: skip


class Daemon:
    def __init__(
        self,
        tmp: Path,
        env: dict[str, str] | None = None,
        *extra: str,
        program: tuple[str, ...] = (),
    ) -> None:
        self.state = tmp / "state"
        self.argv = sdfrd_argv(self.state, *extra, program=program)
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
    # 192.0.2.1 (TEST-NET-1) is no address of this machine: binding it cannot work. (An API
    # off loopback must be allowed, and tokened, to be tried at all.)
    token = tmp_path / "api-token"
    token.write_text("a-token-for-other-machines\n")
    argv = sdfrd_argv(tmp_path / "s2", "--api-allow-remote", "true", "--api-token-file", str(token))
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
    d = Daemon(tmp_path, None, "--layers", "processes")
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
    assert d.health() == "up"  # READY=1 only once both layers serve (discovery not "starting")
    manager.got.clear()
    manager.until("WATCHDOG=1", 2.0)
    manager.got.clear()
    manager.until("WATCHDOG=1", 1.0)  # every half interval
    d.proc.terminate()
    manager.until("STOPPING=1", 10)
    assert d.stop() == 0
    # The layers never got the manager's variables (only the supervisor speaks to it).
    assert "cannot notify systemd" not in d.text()


#: sdfrd with a fault put into its discovery layer's first run (the real daemon otherwise):
#: FAULT=crash raises in its event loop once it has run for 2 s, FAULT=hang blocks that loop.
#: A file next to the state directory says the fault was made: a restarted sdfrd runs clean.
FAULTY_SDFRD = """
import asyncio, os, sys, time
from pathlib import Path
import sdfr.daemon.discovery as discovery
from sdfr.daemon import main

made = Path(os.environ["FAULT_MADE"])
real = discovery._amain

async def faulty(*args):
    if made.exists():
        return await real(*args)
    made.write_text(os.environ["FAULT"])
    task = asyncio.ensure_future(real(*args))
    await asyncio.sleep(2.0)
    if os.environ["FAULT"] == "hang":
        time.sleep(3600)
    raise RuntimeError("injected fault")

discovery._amain = faulty
sys.exit(main(sys.argv[1:]))
"""


def faulty_daemon(tmp_path: Path, fault: str) -> Daemon:
    script = tmp_path / "faulty_sdfrd.py"
    script.write_text(FAULTY_SDFRD)
    env = {"FAULT": fault, "FAULT_MADE": str(tmp_path / "fault-made")}
    return Daemon(tmp_path, env, "--layers", "threads", program=(str(script),))


def threads_of(pid: int) -> dict[str, int]:
    """The named threads of `pid`: comm -> thread id."""
    out = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        out[(task / "comm").read_text().strip()] = int(task.name)
    return out


def test_threads_mode_runs_both_layers_in_one_process(
    tmp_path: Path, daemons: list[Daemon]
) -> None:
    d = Daemon(tmp_path, None, "--layers", "threads")
    daemons.append(d)
    poll("discovery up", lambda: d.health() == "up" or d.health(), 20.0)
    pid = d.proc.pid
    assert d.layers() == {"supervisor": pid, "api": pid, "discovery": pid}
    names = threads_of(pid)
    assert {"sdfrd-api", "sdfrd-discovery"} <= set(names), names
    kids = [p for p in Path("/proc").iterdir() if p.name.isdigit() and p.name != str(pid)]
    assert not [p for p in kids if f"PPid:\t{pid}\n" in (p / "status").read_text(errors="replace")]
    assert d.stop() == 0
    text = d.text()
    assert "api layer started (a thread)" in text and "discovery layer started (a thread)" in text
    assert "discovery stopped (byebye sent)" in text and "sdfrd INFO stopped" in text
    # Each layer's lines in its own format, as with processes.
    assert "sdfrd[discovery] INFO discovery up" in text and "sdfrd[api] INFO" in text


def test_a_failing_layer_thread_is_restarted_while_the_other_serves(
    tmp_path: Path, daemons: list[Daemon]
) -> None:
    d = faulty_daemon(tmp_path, "crash")
    daemons.append(d)
    poll("the fault", lambda: "injected fault" in d.text(), 30.0)
    # The API layer answered throughout, until the new discovery layer is up.
    answers = []
    deadline = time.monotonic() + 20.0
    while time.monotonic() < deadline:
        answers.append(d.health())
        if answers[-1] == "up" and "discovery layer exited" in d.text():
            break
        time.sleep(0.05)
    assert answers[-1] == "up", answers[-5:]
    assert not [a for a in answers if a.startswith("no answer")], answers
    up = "sdfrd[discovery] INFO discovery up"
    poll("a new discovery layer's log", lambda: d.text().count(up) == 2, 10.0)
    text = d.text()
    assert "discovery layer exited (code 1); restarting" in text
    assert "RuntimeError: injected fault" in text
    assert text.count("api layer started (a thread)") == 1  # (the same one)
    assert d.proc.poll() is None and d.layers()["discovery"] == d.proc.pid
    assert d.stop() == 0


def test_a_hung_layer_thread_restarts_the_daemon_in_its_process(
    tmp_path: Path, daemons: list[Daemon]
) -> None:
    d = faulty_daemon(tmp_path, "hang")
    daemons.append(d)
    poll("discovery up", lambda: d.health() == "up" or d.health(), 20.0)
    poll("the hang", lambda: (tmp_path / "fault-made").exists(), 10.0)
    hung_at = time.monotonic()
    poll("sdfrd restarted", lambda: "restarting sdfrd" in d.text(), STALL_AFTER + 15)
    assert time.monotonic() - hung_at >= STALL_AFTER - CHECK_EVERY - 2.0
    poll("up again", lambda: d.health() == "up" or d.health(), 30.0)
    text = d.text()
    assert "discovery layer has not beaten for" in text
    assert "(hung); a thread cannot be killed alone: restarting sdfrd" in text
    assert text.count("fleet 1: open") == 2  # the daemon started again...
    assert d.proc.poll() is None  # ... in the same process (exec)
    assert d.stop() == 0
