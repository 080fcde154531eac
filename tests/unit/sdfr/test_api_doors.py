"""The local API's keyring (unix socket only), its doors (who may knock, what every answer
looks like) and its writes (durable, idempotent, grouped)."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import errno
import json
import os
import socket
import sqlite3
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from aiohttp import ClientSession, UnixConnector
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sdfr.api import (
    MAX_BODY,
    STATE,
    App,
    Runner,
    TCPSite,
    UnixSite,
    create_app,
)
from sdfr.config import keystore
from sdfr.config.load import Config
from sdfr.protocol import auth
from sdfr.protocol.auth import Keyring
from sdfr.store import Store, write_error
from tests.support.api import aio, free_port, raw_exchange, serve, status

# -- the keyring: unix socket only --------------------------------------------------------------


@contextlib.asynccontextmanager
async def over_unix_socket(app: App, path: Path) -> AsyncIterator[ClientSession]:
    runner = Runner(app)
    await runner.setup()
    await UnixSite(runner, str(path)).start()
    try:
        async with ClientSession(connector=UnixConnector(str(path))) as session:
            yield session
    finally:
        await runner.cleanup()


@aio
async def test_key_management_is_refused_over_tcp(cfg: Config, store: Store) -> None:
    async with serve(create_app(cfg, store)) as c:
        for method, path, body in (
            ("GET", "/keys", None),
            ("POST", "/keys", {"key": base64.b64encode(bytes(32)).decode()}),
            ("PUT", "/keys/mode", {"mode": "accept"}),
            ("POST", f"/keys/{auth.key_id(bytes(32))}/use", None),
            ("DELETE", f"/keys/{auth.key_id(bytes(32))}", None),
        ):
            r = await c.request(method, path, json=body)
            assert r.status == 403 and r.content_type == "application/json"
            assert "unix socket" in (await r.json())["error"]
    assert not (cfg.state_dir / "keyring.json").exists()


@aio
async def test_the_keyring_over_the_unix_socket(
    cfg: Config, store: Store, discovery_store: Store, tmp_path_factory: pytest.TempPathFactory
) -> None:
    k1, k2 = bytes(range(32)), bytes(range(5, 37))
    id1, id2 = auth.key_id(k1), auth.key_id(k2)
    b64 = {k: base64.b64encode(k).decode() for k in (k1, k2)}
    sock = tmp_path_factory.mktemp("s") / "api.sock"
    bodies: list[str] = []

    async def call(s: ClientSession, method: str, path: str, body: Any = None) -> Any:
        r = await s.request(method, f"http://localhost{path}", json=body)
        text = await r.text()
        bodies.append(text)
        return r.status, (json.loads(text) if text else None)

    def on_disk() -> Keyring:
        return keystore.load_keyring(cfg.state_dir)

    discovery_store.write_status(status(auth={"mode": "accept", "received": {id1: 12, id2: 1}}))
    async with over_unix_socket(create_app(cfg, store), sock) as s:
        assert await call(s, "GET", "/keys") == (
            200,
            {"mode": "open", "primary": None, "keyed": False, "ssdp_interop": True, "keys": []},
        )
        code, err = await call(s, "PUT", "/keys/mode", {"mode": "sign"})
        assert code == 409 and err["field"] == "mode"  # no key yet: nothing to sign with
        assert not keystore.keyring_path(cfg.state_dir).exists()
        code, ring = await call(s, "POST", "/keys", {"key": b64[k1]})
        assert code == 201 and ring["id"] == id1 and ring["mode"] == "accept"
        assert ring["keys"][0]["received"] == 12 and ring["ssdp_interop"] is False
        assert ring["keys"][0]["primary"] is True
        assert isinstance(ring["keys"][0]["installed"], float)
        assert on_disk() == Keyring.of([k1], mode="accept")
        assert (await call(s, "POST", "/keys", {"key": b64[k1]}))[0] == 200
        code, ring = await call(s, "POST", "/keys", {"key": b64[k2]})
        assert code == 201 and ring["primary"] == id1 and ring["mode"] == "accept"
        assert {k["id"]: k["received"] for k in ring["keys"]} == {id1: 12, id2: 1}
        assert on_disk() == Keyring.of([k1, k2], primary=k1, mode="accept")
        code, ring = await call(s, "POST", f"/keys/{id2}/use")
        assert code == 200 and ring["primary"] == id2
        assert on_disk() == Keyring.of([k1, k2], primary=k2, mode="accept")
        code, err = await call(s, "POST", "/keys/0badc0de/use")
        assert code == 404 and err["field"] == "id"
        code, err = await call(s, "DELETE", f"/keys/{id2}")
        assert code == 409 and err["field"] == "id"
        assert (await call(s, "DELETE", f"/keys/{id1}"))[0] == 204
        assert bodies[-1] == ""
        assert on_disk() == Keyring.of([k2], mode="accept")
        assert (await call(s, "DELETE", f"/keys/{id1}"))[0] == 404
        code, ring = await call(s, "PUT", "/keys/mode", {"mode": "sign"})
        assert code == 200 and ring["mode"] == "sign" and on_disk().mode == "sign"
        code, ring = await call(s, "PUT", "/keys/mode", {"mode": "enforce"})
        assert code == 200 and ring["mode"] == "enforce"
        code, err = await call(s, "PUT", "/keys/mode", {"mode": "lax"})
        assert code == 422 and err["field"] == "mode" and on_disk().mode == "enforce"
        assert (await call(s, "GET", "/keys"))[1] == ring
        code, err = await call(s, "POST", "/keys", {"key": "not base64"})
        assert code == 422 and err["field"] == "key"
        assert (await call(s, "POST", "/keys", {"key": b64[k1], "more": 1}))[0] == 422
    stored = keystore.load(cfg.state_dir)
    assert stored.keyring == Keyring.of([k2], mode="enforce")
    assert not any(b64[k1] in b or b64[k2] in b for b in bodies)  # never key material


@aio
async def test_a_keyring_that_cannot_be_read_or_written_is_named(
    cfg: Config,
    store: Store,
    tmp_path_factory: pytest.TempPathFactory,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    sock = tmp_path_factory.mktemp("s") / "api.sock"
    key = base64.b64encode(bytes(range(32))).decode()
    path = keystore.keyring_path(cfg.state_dir)
    async with over_unix_socket(create_app(cfg, store), sock) as s:

        async def call(method: str, url: str, body: Any = None) -> tuple[int, Any]:
            r = await s.request(method, f"http://localhost{url}", json=body)
            return r.status, await r.json()

        # Damaged: every call says which file and what to do, none overwrites it.
        path.write_text('{"version": 1, "mode": "enforce", "keys": 7}')
        for method, url, body in (
            ("GET", "/keys", None),
            ("POST", "/keys", {"key": key}),
            ("PUT", "/keys/mode", {"mode": "sign"}),
            ("POST", "/keys/0a0b0c0d/use", None),
            ("DELETE", "/keys/0a0b0c0d", None),
        ):
            code, err = await call(method, url, body)
            assert code == 500 and err["field"] == "keyring", (method, url)
            assert str(path) in err["error"] and "damaged" in err["error"]
        assert path.read_text() == '{"version": 1, "mode": "enforce", "keys": 7}'
        path.unlink()
        # A full disk and a read-only one, as the state directory's other writes report them.
        for code_, errno_, says in (
            (507, errno.ENOSPC, "No space"),
            (503, errno.EROFS, "Read-only"),
        ):

            def refuse(target: Path, body: bytes, *, exclusive: bool, e: int = errno_) -> None:
                raise keystore._WriteFailed(target, OSError(e, os.strerror(e)))

            with monkeypatch.context() as m:
                m.setattr(keystore, "_write_private", refuse)
                code, err = await call("POST", "/keys", {"key": key})
            assert code == code_ and err["field"] == "keyring" and says in err["error"]
            assert str(path) in err["error"]
            assert not path.exists()
        # Once it can be written, the same call works.
        assert (await call("POST", "/keys", {"key": key}))[0] == 201


# -- the doors: who may knock, and what every answer looks like ---------------------------------


@aio
async def test_what_a_web_page_can_send_is_refused(cfg: Config, store: Store) -> None:
    body = {"name": "cam", "type": "sensor.camera"}
    async with serve(create_app(cfg, store)) as c:
        for data, ctype in (
            (json.dumps(body), "text/plain"),
            ("name=cam&type=sensor.camera", "application/x-www-form-urlencoded"),
            ('--x\r\nContent-Disposition: form-data; name="a"\r\n\r\n1\r\n--x--\r\n',
             "multipart/form-data; boundary=x"),
        ):  # fmt: skip
            r = await c.post("/services", data=data, headers={"Content-Type": ctype})
            assert r.status == 415, ctype
            assert (await r.json())["field"] == "Content-Type"
        r = await c.post("/services", json=body, headers={"Origin": "http://evil.example"})
        assert r.status == 403 and (await r.json())["field"] == "Origin"
        r = await c.get("/neighbors", headers={"Sec-Fetch-Site": "cross-site"})
        assert r.status == 403
        r = await c.get("/neighbors", headers={"Host": "evil.example"})  # DNS rebinding
        answer = await r.json()
        assert r.status == 403 and answer["field"] == "Host" and "127.0.0.1" in answer["error"]
        assert store.local_state() == (0, [])
        # What programs send is fine: no Origin, the API's own names, JSON bodies.
        for host in ("127.0.0.1:8700", "localhost", "[::1]:8700"):
            assert (await c.get("/neighbors", headers={"Host": host})).status == 200
        r = await c.post("/services", json=body, headers={"Sec-Fetch-Site": "none"})
        assert r.status == 201


@aio
async def test_trusted_pages_and_names_can_be_configured(tmp_path: Path, store: Store) -> None:
    cfg = Config(
        state_dir=store.path.parent,
        robot_id="r1",
        api_allowed_hosts=("robot-7.local",),
        api_allowed_origins=("http://dashboard.local:8080",),
    )
    async with serve(create_app(cfg, store)) as c:
        headers = {"Host": "robot-7.local:8700", "Origin": "http://dashboard.local:8080"}
        assert (await c.get("/neighbors", headers=headers)).status == 200
        headers["Origin"] = "http://dashboard.local:9999"
        assert (await c.get("/neighbors", headers=headers)).status == 403


@aio
async def test_json_nested_deeper_than_any_service_is_a_400(cfg: Config, store: Store) -> None:
    async with serve(create_app(cfg, store)) as c:
        for depth in (10_000, 32_000):
            data = "[" * depth + "]" * depth
            assert len(data) < MAX_BODY
            r = await c.post("/services", data=data, headers={"Content-Type": "application/json"})
            assert r.status == 400 and "nested too deeply" in (await r.json())["error"]


@aio
async def test_errors_before_any_handler_are_json_too(cfg: Config, store: Store) -> None:
    runner = Runner(create_app(cfg, store))
    await runner.setup()
    port = free_port()
    await TCPSite(runner, "127.0.0.1", port).start()
    try:
        many = b"".join(b"X-%d: 1\r\n" % i for i in range(200))
        cases = [
            (b"GET /neighbors?" + b"a" * 9000 + b" HTTP/1.1\r\nHost: x\r\n\r\n", 414, "8190"),
            (b"GET /neighbors HTTP/1.1\r\nHost: x\r\nX-Big: " + b"b" * 9000 + b"\r\n\r\n", 400,
             "8190"),
            (b"GET /neighbors HTTP/1.1\r\nHost: x\r\n" + many + b"\r\n", 400, "headers"),
            (b"FROB /neighbors HTTP/1.1\r\nHost: localhost\r\n\r\n", 400, "method"),
            (b"\x16\x03\x01\x02\x00garbage\r\n\r\n", 400, "malformed"),
        ]  # fmt: skip
        for request, code, says in cases:
            status, headers, raw = await asyncio.to_thread(raw_exchange, port, request)
            assert status == code, (request[:20], status)
            assert headers["content-type"].startswith("application/json")
            body = json.loads(raw)
            assert set(body) == {"error", "field"} and says in body["error"], body
            assert len(body["error"]) < 200  # the request is not echoed back
    finally:
        await runner.cleanup()


# -- publishes: durable, idempotent, grouped ------------------------------------------------------


@aio
async def test_a_publish_retried_under_its_id_is_stored_once(cfg: Config, store: Store) -> None:
    body = {"id": "cam-1", "name": "cam", "type": "sensor.camera", "attributes": {"fps": 30}}
    async with serve(create_app(cfg, store)) as c:
        r = await c.post("/services", json=body)
        assert r.status == 201 and (await r.json())["id"] == "cam-1"
        first = await r.json()
        r = await c.post("/services", json=body)  # the client never saw the first answer
        assert r.status == 200 and await r.json() == first
        r = await c.post("/services", json={**body, "name": "another camera"})
        assert r.status == 409 and (await r.json())["field"] == "id"
        # Two copies in flight at once: one stores it, the other finds it stored.
        body2 = {**body, "id": "cam-2"}
        answers = await asyncio.gather(*(c.post("/services", json=body2) for _ in range(2)))
        assert sorted(a.status for a in answers) == [200, 201]
    version, services = store.local_state()
    assert [s.id for s in services] == ["cam-1", "cam-2"] and version == 2


@pytest.mark.parametrize("disk", ["fast", "slow"])
@aio
async def test_a_burst_of_publishes_is_all_stored(cfg: Config, store: Store, disk: str) -> None:
    """On a fast disk each commit's fsync runs inline; on a slow one (here: told its fsyncs
    take 50 ms) in a thread, and the requests arriving meanwhile share the next commit."""
    app = create_app(cfg, store)
    writer = app[STATE].writer
    if disk == "slow":
        writer.fsync_avg = 0.05
    async with serve(app) as c:
        answers = await asyncio.gather(
            *(c.post("/services", json={"name": f"s{i}", "type": "t"}) for i in range(60))
        )
        assert all(a.status == 201 for a in answers)
        versions = sorted([(await a.json())["version"] for a in answers])
        assert versions == list(range(1, 61))  # each its own version, none lost
        if disk == "slow":
            assert writer.commits < 60
    assert len(store.local_state()[1]) == 60


@aio
async def test_a_half_sent_request_is_dropped(cfg: Config, store: Store) -> None:
    runner = Runner(create_app(cfg, store), keepalive_timeout=0.5)
    await runner.setup()
    port = free_port()
    await TCPSite(runner, "127.0.0.1", port).start()

    def slowloris() -> float:
        with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
            sock.sendall(b"GET /neighbors HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
            t0 = time.monotonic()
            while sock.recv(1024):  # the server closes it
                pass
            return time.monotonic() - t0

    try:
        took = await asyncio.to_thread(slowloris)
        assert took < 3.0
    finally:
        await runner.cleanup()


@aio
async def test_a_read_only_state_dir_is_a_503_naming_it(cfg: Config, store: Store) -> None:
    app = create_app(cfg, store)
    async with serve(app) as c:
        assert (await c.post("/services", json={"name": "a", "type": "t"})).status == 201
        # SQLite's own read-only answer, as a read-only filesystem gives it.
        writer = app[STATE].writer
        assert writer._store is not None
        writer._store._db.execute("PRAGMA query_only=ON")
        r = await c.post("/services", json={"name": "b", "type": "t"})
        answer = await r.json()
        assert r.status == 503 and answer["field"] == "state_dir"
        assert "read-only" in answer["error"] and str(cfg.state_dir) in answer["error"]
        health = await (await c.get("/health")).json()
        assert health["state"] == "read-only" and str(cfg.state_dir) in health["state_error"]
        writer._store._db.execute("PRAGMA query_only=OFF")
        assert (await c.post("/services", json={"name": "b", "type": "t"})).status == 201
        assert (await (await c.get("/health")).json())["state"] == "ok"


def test_write_failures_are_told_apart() -> None:
    where = Path("/var/lib/sdfr")
    full = write_error(where, OSError(errno.ENOSPC, "No space left on device"))
    assert full.reason == "full" and "is full" in str(full) and str(where) in str(full)
    assert write_error(where, sqlite3.OperationalError("database or disk is full")).reason == "full"
    ro = write_error(where, OSError(errno.EROFS, "Read-only file system"))
    assert ro.reason == "read-only"
    assert (
        write_error(where, sqlite3.OperationalError("attempt to write a readonly database")).reason
        == "read-only"
    )
    assert write_error(where, sqlite3.OperationalError("disk I/O error")).reason == "error"


JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=40),
    lambda inner: (
        st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=12), inner, max_size=5)
    ),
    max_leaves=30,
)


@settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck))
@given(
    body=JSON
    | st.dictionaries(
        st.sampled_from(["id", "name", "type", "url", "attributes", "x"]), JSON, max_size=6
    ),
    query=st.dictionaries(st.text(min_size=1, max_size=12), st.text(max_size=20), max_size=4),
)
def test_no_input_makes_a_500(
    tmp_path_factory: pytest.TempPathFactory, body: Any, query: dict[str, str]
) -> None:
    state_dir = tmp_path_factory.mktemp("fuzz")

    async def check() -> None:
        store = Store(state_dir)
        try:
            async with serve(create_app(Config(state_dir=state_dir, robot_id="r1"), store)) as c:
                for method, path, kw in (
                    ("POST", "/services", {"json": body}),
                    ("GET", "/neighbors/search", {"params": query}),
                    ("GET", "/neighbors", {"params": query}),
                    ("DELETE", f"/services/{str(body)[:30]}", {}),
                ):
                    r = await c.request(method, path, **kw)
                    assert r.status < 500, (method, path, r.status, await r.text())
                    answer = await r.json() if r.status != 204 else {}
                    assert r.status < 300 or set(answer) == {"error", "field"}
        finally:
            store.close()

    asyncio.run(check())
