"""/health says "starting" until the discovery layer speaks on the fleet's network: a layer
that is alive but whose start has not finished (or failed: its description's port taken) is
not "up", and a robot reported healthy is one that discovers.

Needs root for the discovery layer's socket (SO_BINDTODEVICE).
"""

from __future__ import annotations

import asyncio
import os
import socket
from dataclasses import replace
from typing import Any

import pytest

from sdfr.api import create_app
from sdfr.config.load import Config
from sdfr.daemon.discovery import DiscoveryLayer
from sdfr.errors import SdfrError
from sdfr.store import Store
from tests.support.api import aio, free_port, serve

pytestmark = pytest.mark.skipif(os.geteuid() != 0, reason="SO_BINDTODEVICE needs root")


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


async def _health(cfg: Config, store: Store) -> tuple[int, dict[str, Any]]:
    async with serve(create_app(cfg, store)) as api:
        r = await api.get("/health")
        return r.status, await r.json()


@aio
async def test_health_is_starting_until_the_layer_speaks_then_up(cfg: Config, store: Store) -> None:
    cfg = replace(cfg, port=_free_udp_port(), describe=f"127.0.0.1:{free_port()}")
    layer = DiscoveryLayer(cfg, store)
    layer._write_status()  # what `run` writes before its start: alive, not yet discovering
    status, health = await _health(cfg, store)
    assert (status, health["status"], health["discovery"]) == (503, "degraded", "starting")
    task = asyncio.create_task(layer.run())
    try:
        for _ in range(200):
            await asyncio.sleep(0.02)
            status, health = await _health(cfg, store)
            if health["discovery"] != "starting":
                break
        assert (status, health["status"], health["discovery"]) == (200, "ok", "up"), health
    finally:
        layer._stopping.set()
        await asyncio.wait_for(task, 10)


@aio
async def test_a_start_that_fails_is_never_reported_up(cfg: Config, store: Store) -> None:
    """The description's port is taken: the layer's start fails, and /health never said up
    (its status file stays "starting" until the supervisor's next try or the pid is gone)."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        host, port = taken.getsockname()
        cfg = replace(cfg, port=_free_udp_port(), describe=f"{host}:{port}")
        layer = DiscoveryLayer(cfg, store)
        with pytest.raises(SdfrError, match=f"describe: cannot listen on {host}:{port}"):
            await asyncio.wait_for(layer.run(), 10)
        for sock in (layer.sock, layer.control, layer.out.to_api.sock):
            sock.close()
    status, health = await _health(cfg, store)
    assert (status, health["discovery"]) == (503, "starting"), health


@aio
async def test_a_slow_look_at_the_wifi_never_holds_back_the_discovery_loop(
    cfg: Config, store: Store, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`iw station dump` runs in a thread: while it takes 1.5 s the layer's event loop goes on
    (beacons, answers, the API's status), and what it found then reaches the status record."""
    import time

    from sdfr.host import wifiwatch

    def slow_dump(iface: str, timeout: float = 5.0) -> dict[str, wifiwatch.Station]:
        time.sleep(1.5)
        return {"02:00:00:00:00:09": wifiwatch.Station("02:00:00:00:00:09", False)}

    monkeypatch.setattr(wifiwatch, "station_dump", slow_dump)
    cfg = replace(cfg, port=_free_udp_port(), describe=f"127.0.0.1:{free_port()}")
    layer = DiscoveryLayer(cfg, store)
    layer.wifi = wifiwatch.Watch("lo", "sdfr-7", "ibss")
    task = asyncio.create_task(layer.run())
    try:
        await asyncio.sleep(0.2)
        loop = asyncio.get_running_loop()
        loop.call_later(0.05, layer._watch_wifi)  # (as the layer's periodic duties call it)
        loop.call_later(0.1, layer._watch_wifi)  # one look at a time: this one starts none
        worst, deadline = 0.0, time.monotonic() + 10
        while layer.wifi_state is None and time.monotonic() < deadline:
            before = time.monotonic()
            await asyncio.sleep(0.01)
            worst = max(worst, time.monotonic() - before - 0.01)
        assert layer.wifi_state is not None, "the look never ended"
        assert layer.wifi_state.authorized == 0
        assert worst < 0.5, f"the loop was held back {worst:.2f} s while iw ran"
    finally:
        layer._stopping.set()
        await asyncio.wait_for(task, 10)
