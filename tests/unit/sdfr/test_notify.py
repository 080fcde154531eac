"""sd_notify against real unix datagram sockets (a path, and the abstract namespace)."""

from __future__ import annotations

import asyncio
import os
import socket
import threading
from pathlib import Path

import pytest

from sdfr.daemon import notify


def test_notify_sends_assignments_to_a_path_socket(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = str(tmp_path / "n.sock")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as manager:
        manager.bind(path)
        monkeypatch.setenv("NOTIFY_SOCKET", path)
        assert notify.notify("READY=1", "STATUS=serving")
        assert manager.recv(100) == b"READY=1\nSTATUS=serving"


def test_notify_abstract_namespace(monkeypatch: pytest.MonkeyPatch) -> None:
    name = f"sdfr-test-{os.getpid()}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as manager:
        manager.bind("\0" + name)
        monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)
        assert notify.notify("WATCHDOG=1")
        assert manager.recv(100) == b"WATCHDOG=1"


def test_without_a_manager_nothing_is_sent(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert not notify.notify("READY=1")
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "nobody.sock"))
    assert not notify.notify("READY=1")  # a socket that is not there: said, not raised
    assert "cannot notify systemd" in caplog.text


def test_watchdog_interval_is_for_this_process_only(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    monkeypatch.delenv("WATCHDOG_USEC", raising=False)
    assert notify.watchdog_interval() is None
    monkeypatch.setenv("WATCHDOG_USEC", "3000000")
    assert notify.watchdog_interval() == 3.0
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    assert notify.watchdog_interval() == 3.0
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid() + 1))
    assert notify.watchdog_interval() is None


def test_beat_writes_to_the_pipe_it_is_given(monkeypatch: pytest.MonkeyPatch) -> None:
    r, w = os.pipe2(os.O_NONBLOCK)
    try:
        monkeypatch.setenv(notify.HEARTBEAT_ENV, str(w))
        notify.beat()
        notify.beat()
        assert os.read(r, 10) == b".."
        for _ in range(70000):  # a full pipe never blocks a layer
            notify.beat()
    finally:
        os.close(r)
        os.close(w)


def test_a_layer_thread_beats_on_its_own_pipe_and_stops_on_its_supervisors_word() -> None:
    """--layers threads: each layer thread has its pipe and its Stopper; a stop asked before
    the layer left its callback still reaches it."""
    got: dict[str, object] = {}

    def layer(name: str, stopper: notify.Stopper, early: bool) -> None:
        r, w = os.pipe2(os.O_NONBLOCK)
        notify.host_thread(w, stopper)
        notify.beat()
        got[f"{name} beat"] = os.read(r, 10)

        async def run() -> None:
            stop = asyncio.Event()
            if early:
                stopper.stop()  # before the callback is left
            notify.on_stop(asyncio.get_running_loop(), stop.set)
            ready.set()
            await asyncio.wait_for(stop.wait(), 10)

        asyncio.run(run())
        got[f"{name} stopped"] = True
        os.close(r)
        os.close(w)

    ready = threading.Event()
    stopper = notify.Stopper()
    t = threading.Thread(target=layer, args=("a", stopper, False))
    t.start()
    assert ready.wait(10)
    stopper.stop()  # from another thread
    t.join(10)
    early = threading.Thread(target=layer, args=("b", notify.Stopper(), True))
    early.start()
    early.join(10)
    assert got == {"a beat": b".", "a stopped": True, "b beat": b".", "b stopped": True}
    assert not t.is_alive() and not early.is_alive()
