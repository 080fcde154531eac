"""Every 2xx that changed or confirmed a registration is on disk before it is sent, and a
write that could not be made durable changed nothing: not committed, not in the event log,
not announced, answered 5xx in JSON."""

from __future__ import annotations

import socket
import sqlite3
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from aiohttp import ClientSession

from sdfr.api import create_app
from sdfr.config.load import Config
from sdfr.store import Store
from tests.support.api import aio, serve

#: PRAGMA synchronous: NORMAL commits are not fsynced in WAL mode; FULL ones are, before
#: the commit is visible to any reader.
NORMAL, FULL = 1, 2


class Disk:
    """The writer's disk: every commit's synchronous level, and a switch that makes the
    fsync of a durable commit fail as SQLite reports it ("disk I/O error")."""

    def __init__(self) -> None:
        self.broken = False
        self.commits: list[int] = []

    def store(self, state_dir: Path) -> Store:
        disk = self

        class OnThisDisk(Store):
            def _commit(self) -> None:
                level = int(self._db.execute("PRAGMA synchronous").fetchone()[0])
                disk.commits.append(level)
                if disk.broken and level >= FULL:
                    raise sqlite3.OperationalError("disk I/O error")
                super()._commit()

        return OnThisDisk(state_dir)


@pytest.fixture
def announced(cfg: Config) -> Iterator[socket.socket]:
    """The discovery layer's socket: what the API layer tells it to announce."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(cfg.state_dir / "discovery.sock"))
    sock.setblocking(False)
    yield sock
    sock.close()


def drain(sock: socket.socket) -> list[bytes]:
    out = []
    while True:
        try:
            out.append(sock.recv(4096))
        except BlockingIOError:
            return out


async def call(c: ClientSession, method: str, path: str, body: Any = None) -> tuple[int, Any]:
    r = await c.request(method, path, json=body)
    return r.status, (await r.json() if r.status != 204 else None)


CAM = {"id": "cam-1", "name": "cam", "type": "camera/rgb", "ttl": 60}


@aio
async def test_a_publish_retried_on_the_renew_path_is_fsynced(cfg: Config, store: Store) -> None:
    disk = Disk()
    async with serve(create_app(cfg, store, writer_store=disk.store)) as c:
        assert (await call(c, "POST", "/services", CAM))[0] == 201
        assert disk.commits[-1] == FULL
        code, again = await call(c, "POST", "/services", {**CAM, "ttl": 120})
        assert code == 200 and again["ttl"] == 120.0
        assert disk.commits[-1] == FULL  # the 200 confirms a registration: on disk first
        assert (await call(c, "POST", "/services", CAM))[0] == 200
        assert disk.commits[-1] == FULL
        # A plain renewal moves the lease's end only: not fsynced (its owner renews again).
        assert (await call(c, "POST", "/services/cam-1/renew"))[0] == 200
        assert disk.commits[-1] == NORMAL
        assert (await call(c, "DELETE", "/services/cam-1"))[0] == 204
        assert disk.commits[-1] == FULL


@aio
async def test_a_write_that_cannot_be_made_durable_changes_nothing(
    cfg: Config, store: Store, announced: socket.socket
) -> None:
    disk = Disk()
    async with serve(create_app(cfg, store, writer_store=disk.store)) as c:
        assert (await call(c, "POST", "/services", CAM))[0] == 201
        drain(announced)
        before = (store.local_state(), store.lease("cam-1"), store.last_event_id())
        disk.broken = True
        for method, path, body in (
            ("POST", "/services", {"id": "lidar", "name": "lidar", "type": "lidar"}),
            ("POST", "/services", {**CAM, "ttl": 5}),  # a retry that changes the lease
            ("DELETE", "/services/cam-1", None),
        ):
            code, err = await call(c, method, path, body)
            assert code == 503, (method, path, code, err)
            assert err["field"] == "state_dir" and "disk I/O error" in err["error"]
            # Not committed (another connection, as the discovery layer's, sees nothing),
            # not in the event log, not announced.
            assert (store.local_state(), store.lease("cam-1"), store.last_event_id()) == before
            assert drain(announced) == []
            assert (await call(c, "GET", "/services"))[1]["version"] == before[0][0]
        health = (await call(c, "GET", "/health"))[1]
        assert health["state"] == "error" and "disk I/O error" in health["state_error"]
        disk.broken = False  # the disk is back: the same requests work
        assert (await call(c, "POST", "/services", {"id": "lidar", "name": "l", "type": "l"}))[
            0
        ] == 201
        assert (await call(c, "DELETE", "/services/cam-1"))[0] == 204
        assert drain(announced)
        assert [s.id for s in store.local_state()[1]] == ["lidar"]
