"""A robot left out of a key rotation is not cut off in silence: the discovery layer of a real
daemon on `lo` receives its datagrams (sealed with a key the keyring does not hold) and the log,
/health and `sdfr keys list` name the key id and where they come from, until they stop.

Needs root for the discovery layer's socket (SO_BINDTODEVICE).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import select
import socket
import time
from collections.abc import AsyncIterator, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from aiohttp import ClientSession, UnixConnector

from sdfr import cli, wire
from sdfr.api import App, Runner, UnixSite, create_app
from sdfr.config import keystore
from sdfr.config.keystore import StoredKeyring
from sdfr.config.load import Config
from sdfr.daemon.channel import CONTROL_SOCKET
from sdfr.daemon.discovery import DiscoveryLayer
from sdfr.protocol import auth
from sdfr.protocol.auth import Keyring
from sdfr.records.model import service_digest
from sdfr.store import Store
from tests.support.api import aio, free_port
from tests.support.logged import logged

pytestmark = pytest.mark.skipif(os.geteuid() != 0, reason="SO_BINDTODEVICE needs root")

OURS = bytes(range(32))
RETIRED = bytes(range(7, 39))  # the key the left-out robot still signs with
WINDOW = 1.0  # the miss window: beacon_interval * miss_limit


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@pytest.fixture
def keyed(cfg: Config) -> Iterator[Config]:
    """A robot of a keyed fleet on `lo`, its keyring holding only the fleet's current key."""
    keystore.save(cfg.state_dir, StoredKeyring(Keyring.of([OURS], mode="enforce")))
    yield replace(
        cfg,
        port=_free_udp_port(),
        describe=f"127.0.0.1:{free_port()}",
        beacon_interval=0.5,
        miss_limit=2,
    )


def _beacon(counter: int) -> bytes:
    """A beacon of r3, sealed with the retired key, from 127.0.0.1."""
    origin = wire.Origin(7, "r3", 1_700_000_000, 1, service_digest(()))
    data = wire.encode(wire.Alive(origin, "http://10.7.0.3:8701/d", 30))
    try:  # a seal bound to its sender's address
        return auth.seal(data, RETIRED, counter, sender="127.0.0.1")
    except TypeError:  # a seal of the trust core that binds nothing
        return auth.seal(data, RETIRED, counter)


@contextlib.contextmanager
def _layer(cfg: Config, store: Store) -> Iterator[DiscoveryLayer]:
    layer = DiscoveryLayer(cfg, store)
    # Its loop does not run here: the API layer is to read the status file it writes, not ask
    # it on its control socket (and wait for an answer that never comes).
    (cfg.state_dir / CONTROL_SOCKET).unlink()
    layer._starting = False  # as after its start, which needs the loop
    try:
        yield layer
    finally:
        for sock in (layer.sock, layer.control, layer.out.to_api.sock):
            sock.close()
        layer.describe.close()


def _deliver(layer: DiscoveryLayer, cfg: Config, datagrams: list[bytes]) -> None:
    """Send `datagrams` to the layer's socket from 127.0.0.1 and let it read them."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as out:
        for data in datagrams:
            out.sendto(data, ("127.0.0.1", cfg.port))
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline:
        ready, _, _ = select.select([layer.sock], [], [], 0.05)
        if not ready:
            if layer.core.counters.rejects["unknown-key"] >= len(datagrams):
                return
            continue
        layer._receive()
    raise AssertionError(f"the layer read {layer.core.counters.rejects} of {len(datagrams)}")


@contextlib.asynccontextmanager
async def _api(app: App, path: Path) -> AsyncIterator[ClientSession]:
    runner = Runner(app)
    await runner.setup()
    await UnixSite(runner, str(path)).start()
    try:
        async with ClientSession(connector=UnixConnector(str(path))) as session:
            yield session
    finally:
        await runner.cleanup()


async def _get(session: ClientSession, path: str) -> Any:
    r = await session.get(f"http://localhost{path}")
    assert r.status in (200, 503), await r.text()
    return await r.json()


@aio
async def test_a_robot_left_out_of_a_rotation_is_named_until_it_stops(
    keyed: Config, store: Store, tmp_path_factory: pytest.TempPathFactory
) -> None:
    cfg = keyed
    sock = tmp_path_factory.mktemp("s") / "api.sock"
    kid = auth.key_id(RETIRED)
    with _layer(cfg, store) as layer, logged("sdfrd.discovery", level=logging.WARNING) as said:
        _deliver(layer, cfg, [_beacon(n) for n in range(1, 4)])
        assert layer.core.counters.rejects["unknown-key"] == 3  # refused, as before
        assert not layer.core.peers  # and nothing of it believed
        # The log names the key id and where it comes from, once for the three datagrams.
        [warning] = said
        assert kid in warning and "127.0.0.1" in warning and "sdfr keys" in warning
        layer._write_status()
        async with _api(create_app(cfg, store), sock) as api:
            health = await _get(api, "/health")
            assert health["status"] == "warning", health
            [why] = [w for w in health["warnings"] if kid in w]
            assert "127.0.0.1" in why and "3 datagrams" in why
            keys = await _get(api, "/keys")
            [seen] = keys["unknown"]
            assert (seen["id"], seen["address"], seen["count"]) == (kid, "127.0.0.1", 3)
            assert time.time() - 5 < seen["last_seen"] <= time.time()
            assert kid not in {k["id"] for k in keys["keys"]}
            shown = cli.keys.show_keys(keys)
            assert kid in shown and "127.0.0.1" in shown
            # They stop (say the robot got the key): after the miss window, all clear.
            await asyncio.sleep(WINDOW + 0.2)
            layer._write_status()
            health = await _get(api, "/health")
            assert health["status"] == "ok" and health["warnings"] == [], health
            keys = await _get(api, "/keys")
            assert "unknown" not in keys  # (as before any came)
            assert kid not in cli.keys.show_keys(keys)
