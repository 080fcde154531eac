"""The channel between the layers: its datagrams on real unix sockets, and the heartbeat pipe
and Stopper a supervisor hands a layer."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import threading
from pathlib import Path

from sdfr.daemon import channel
from sdfr.daemon.channel import Host, Stopper


def test_the_datagrams_keep_their_bytes() -> None:
    assert (channel.SERVICES, channel.STATUS, channel.EVENTS) == (
        b"services\n",
        b"status\n",
        b"events\n",
    )
    assert (channel.STATUS_SOCKET, channel.CONTROL_SOCKET) == ("status.sock", "discovery.sock")


def test_the_api_layer_wakes_the_discovery_layer_and_asks_for_its_status(tmp_path: Path) -> None:
    assert not channel.notify_discovery(tmp_path)  # nobody listening: silently nothing
    control = channel.open_control(tmp_path)
    try:
        assert (tmp_path / "discovery.sock").stat().st_mode & 0o777 == 0o660
        assert not channel.status_asked(control)  # nothing waiting
        assert channel.notify_discovery(tmp_path)
        assert not channel.status_asked(control)  # SERVICES: not the status
        assert channel.notify_discovery(tmp_path)
        assert channel.notify_discovery(tmp_path, channel.STATUS)
        assert channel.status_asked(control)  # both read, one of them asked
        assert not channel.status_asked(control)
    finally:
        channel.close_control(control, tmp_path)
    assert not (tmp_path / "discovery.sock").exists()


def test_the_discovery_layer_sends_status_and_events_read_at_their_size(tmp_path: Path) -> None:
    to_api = channel.ToApi(tmp_path)
    to_api.send(channel.EVENTS)  # no API layer listening: dropped
    record = json.dumps({"pid": 1, "heartbeat": 2.0, "pad": "x" * 100_000}).encode()
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as listener:
        listener.bind(str(tmp_path / channel.STATUS_SOCKET))
        listener.setblocking(False)
        to_api.send(record)
        to_api.send(channel.EVENTS)
        assert list(channel.receive(listener, bytearray(1))) == [record, channel.EVENTS]
        assert list(channel.receive(listener, bytearray(1))) == []
    to_api.sock.close()


def test_beat_writes_to_the_pipe_it_is_given() -> None:
    Host().beat()  # a layer that runs alone: nothing
    r, w = os.pipe2(os.O_NONBLOCK)
    try:
        host = Host(w)
        host.beat()
        host.beat()
        assert os.read(r, 10) == b".."
        for _ in range(70000):  # a full pipe never blocks a layer
            host.beat()
    finally:
        os.close(r)
        os.close(w)


def test_a_layer_thread_beats_on_its_own_pipe_and_stops_on_its_supervisors_word() -> None:
    """--layers threads: each layer thread has its pipe and its Stopper; a stop asked before
    the layer left its callback still reaches it."""
    got: dict[str, object] = {}

    def layer(name: str, stopper: Stopper, early: bool) -> None:
        r, w = os.pipe2(os.O_NONBLOCK)
        host = Host(w, stopper)
        host.beat()
        got[f"{name} beat"] = os.read(r, 10)

        async def run() -> None:
            stop = asyncio.Event()
            if early:
                stopper.stop()  # before the callback is left
            host.on_stop(asyncio.get_running_loop(), stop.set)
            ready.set()
            await asyncio.wait_for(stop.wait(), 10)

        asyncio.run(run())
        got[f"{name} stopped"] = True
        os.close(r)
        os.close(w)

    ready = threading.Event()
    stopper = Stopper()
    t = threading.Thread(target=layer, args=("a", stopper, False))
    t.start()
    assert ready.wait(10)
    stopper.stop()  # from another thread
    t.join(10)
    early = threading.Thread(target=layer, args=("b", Stopper(), True))
    early.start()
    early.join(10)
    assert got == {"a beat": b".", "a stopped": True, "b beat": b".", "b stopped": True}
    assert not t.is_alive() and not early.is_alive()
