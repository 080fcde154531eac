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
