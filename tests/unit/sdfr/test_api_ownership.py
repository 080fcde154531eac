"""A service belongs to the program that published it: its owner token, or on the unix
socket its user. Others may read it, not unpublish, renew, hold or replace it; and no one
client may take every event stream."""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import http.client
import json
import os
import socket
import sqlite3
import tempfile
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest

from sdfr.api import Runner, TCPSite, UnixSite, create_app
from sdfr.api.events import STREAMS_MAX
from sdfr.cli import main as sdfr
from sdfr.config.load import Config
from sdfr.ros.core import Bridge, ServiceRequest
from sdfr.ros.params import NodeParams
from sdfr.store import Store
from tests.support.api import ApiLayer, aio, free_port
from tests.unit.sdfr.test_ros_core import Recorder

OWNER = "X-SDFR-Owner"
CAM = {"id": "cam-1", "name": "cam", "type": "camera/rgb", "ttl": 60}
#: Users that are not root (nobody, and one more with no name: a uid is all the kernel needs).
USER_A, USER_B = 65534, 65533


@contextlib.asynccontextmanager
async def served(cfg: Config, store: Store) -> AsyncIterator[tuple[int, Path]]:
    """The API on a free TCP port and on a unix socket every user may open: (port, path)."""
    runner = Runner(create_app(cfg, store))
    await runner.setup()
    port = free_port()
    await TCPSite(runner, "127.0.0.1", port).start()
    where = Path(tempfile.mkdtemp(prefix="sdfr-own-"))
    where.chmod(0o755)
    path = where / "api.sock"
    await UnixSite(runner, str(path)).start()
    path.chmod(0o666)
    try:
        yield port, path
    finally:
        await runner.cleanup()
        path.unlink(missing_ok=True)
        where.rmdir()


def connect_as(uid: int, address: str | tuple[str, int]) -> socket.socket:
    """A socket connected to `address` (a unix socket's path, or (host, port)) by a process
    running as `uid`: the server sees that user as its peer (SO_PEERCRED on a unix socket,
    the socket's owner in /proc/net/tcp on TCP). The child connects, hands the socket over
    (SCM_RIGHTS) and exits."""
    parent, child = socket.socketpair()
    pid = os.fork()
    if pid == 0:  # pragma: no cover (the child)
        code = 1
        try:
            os.setgroups([])
            os.setgid(uid)
            os.setuid(uid)
            family = socket.AF_UNIX if isinstance(address, str) else socket.AF_INET
            sock = socket.socket(family, socket.SOCK_STREAM)
            sock.connect(address)
            socket.send_fds(child, [b"s"], [sock.fileno()])
            code = 0
        finally:
            os._exit(code)
    child.close()
    try:
        _, fds, _, _ = socket.recv_fds(parent, 1, 1)
    finally:
        parent.close()
        _, status = os.waitpid(pid, 0)
    assert fds, f"a process as uid {uid} could not connect to {address} (status {status})"
    return socket.socket(fileno=fds[0])


def exchange(
    sock: socket.socket, method: str, path: str, body: Any = None, **headers: str
) -> tuple[int, Any]:
    """One request on a connected socket: the status and the JSON answer (None if empty)."""
    conn = http.client.HTTPConnection("localhost", timeout=5)
    conn.sock = sock
    data = None if body is None else json.dumps(body).encode()
    head = {"Content-Type": "application/json"} if data is not None else {}
    conn.request(method, path, body=data, headers={**head, **headers})
    resp = conn.getresponse()
    raw = resp.read()
    conn.close()
    return resp.status, json.loads(raw) if raw else None


def as_user(uid: int | None, where: str | tuple[str, int]) -> socket.socket:
    """A connection by `uid` (None: this process, root)."""
    if uid is not None:
        return connect_as(uid, where)
    family = socket.AF_UNIX if isinstance(where, str) else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.connect(where)
    return sock


async def call(
    uid: int | None, where: str | tuple[str, int], method: str, path: str, body: Any = None,
    **headers: str,
) -> tuple[int, Any]:  # fmt: skip
    return await asyncio.to_thread(
        lambda: exchange(as_user(uid, where), method, path, body, **headers)
    )


def need_root() -> None:
    if os.geteuid() != 0:
        pytest.skip("needs root: the test connects as other users")


# -- the owner token ---------------------------------------------------------------------------


@aio
async def test_only_the_owner_token_unpublishes_renews_holds_or_replaces(
    cfg: Config, store: Store
) -> None:
    async with served(cfg, store) as (port, _):
        tcp = ("127.0.0.1", port)
        code, made = await call(None, tcp, "POST", "/services", CAM)
        assert code == 201
        token = made["owner_token"]
        assert isinstance(token, str) and len(token) >= 22
        before = store.lease("cam-1")
        # Any program may read it...
        assert (await call(None, tcp, "GET", "/services/cam-1"))[0] == 200
        assert [s["id"] for s in (await call(None, tcp, "GET", "/services"))[1]["services"]] == [
            "cam-1"
        ]
        # ... none but its owner may change it: without the token, or with another one.
        for headers in ({}, {OWNER: "another-program-s-token-0123456789"}):
            for method, path, body in (
                ("DELETE", "/services/cam-1", None),
                ("POST", "/services/cam-1/renew", {"ttl": 1}),
                ("POST", "/services/cam-1/hold", None),
                ("POST", "/services", {**CAM, "ttl": 1}),  # a "retry" that shortens the lease
                ("POST", "/services", CAM),
            ):
                code, err = await call(None, tcp, method, path, body, **headers)
                assert code == 403, (method, path, headers, code, err)
                assert err["field"] == OWNER and "owner" in err["error"], err
                assert "unix socket" in err["error"]  # says the other way in
        assert store.get_service("cam-1") is not None and store.lease("cam-1") == before
        # Its owner may.
        mine = {OWNER: token}
        code, again = await call(None, tcp, "POST", "/services", CAM, **mine)
        assert code == 200 and again["owner_token"] == token
        assert (await call(None, tcp, "POST", "/services/cam-1/renew", None, **mine))[0] == 200
        assert (await call(None, tcp, "DELETE", "/services/cam-1", None, **mine))[0] == 204
    assert store.local_state()[1] == []


@aio
async def test_a_token_chosen_by_the_client_makes_its_retries_its_own(
    cfg: Config, store: Store
) -> None:
    """A client that sends its own token with the publish can retry it after a lost answer
    (it never saw a token from the daemon)."""
    mine = {OWNER: "a-clients-own-token-chosen-before-sending"}
    async with served(cfg, store) as (port, _):
        tcp = ("127.0.0.1", port)
        code, made = await call(None, tcp, "POST", "/services", CAM, **mine)
        assert code == 201 and made["owner_token"] == mine[OWNER]
        code, again = await call(None, tcp, "POST", "/services", CAM, **mine)
        assert code == 200 and again["id"] == "cam-1"
        for bad in ("short", "spaces are not allowed in a token here", "é" * 30):
            code, err = await call(None, tcp, "POST", "/services", {**CAM, "id": "x"}, **{
                OWNER: bad
            })  # fmt: skip
            assert code == 400 and err["field"] == OWNER, (bad, err)


@aio
async def test_tokens_are_stored_hashed_and_outlive_a_restart(cfg: Config, tmp_path: Path) -> None:
    mine = {OWNER: "a-token-that-must-never-be-stored-as-is"}
    store = Store(cfg.state_dir)
    try:
        async with served(cfg, store) as (port, _):
            assert (await call(None, ("127.0.0.1", port), "POST", "/services", CAM, **mine))[
                0
            ] == 201
    finally:
        store.close()
    raw = b"".join(p.read_bytes() for p in cfg.state_dir.glob("state.db*"))
    assert mine[OWNER].encode() not in raw
    with contextlib.closing(sqlite3.connect(cfg.state_dir / "state.db")) as db:
        text = " ".join(str(v) for row in db.execute("SELECT * FROM local_services") for v in row)
    assert hashlib.sha256(mine[OWNER].encode()).hexdigest() in text
    store = Store(cfg.state_dir)  # the daemon again, on the same state directory
    try:
        async with served(cfg, store) as (port, _):
            tcp = ("127.0.0.1", port)
            assert (await call(None, tcp, "DELETE", "/services/cam-1"))[0] == 403
            assert (await call(None, tcp, "DELETE", "/services/cam-1", None, **mine))[0] == 204
    finally:
        store.close()


# -- the unix socket: the publishing user, and root -----------------------------------------------


@aio
async def test_on_the_unix_socket_a_service_belongs_to_the_user_that_published_it(
    cfg: Config, store: Store
) -> None:
    need_root()
    async with served(cfg, store) as (port, path):
        unix = str(path)
        code, made = await call(USER_A, unix, "POST", "/services", CAM)
        assert code == 201 and made["owner_token"]
        # Another user, on the socket or over TCP: may read, not change.
        assert (await call(USER_B, unix, "GET", "/services/cam-1"))[0] == 200
        for uid, where in ((USER_B, unix), (USER_B, ("127.0.0.1", port))):
            for method, p, body in (
                ("DELETE", "/services/cam-1", None),
                ("POST", "/services/cam-1/renew", None),
                ("POST", "/services", {**CAM, "ttl": 1}),
            ):
                code, err = await call(uid, where, method, p, body)
                assert code == 403 and err["field"] == OWNER, (where, method, code, err)
        # Its user (another of its programs, without the token) may renew and unpublish it.
        assert (await call(USER_A, unix, "POST", "/services/cam-1/renew"))[0] == 200
        assert (await call(USER_A, unix, "DELETE", "/services/cam-1"))[0] == 204
        # Root on the unix socket may change anyone's.
        assert (await call(USER_A, unix, "POST", "/services", CAM))[0] == 201
        assert (await call(None, unix, "DELETE", "/services/cam-1"))[0] == 204
        # Root over TCP is just a program without the token.
        assert (await call(USER_A, unix, "POST", "/services", CAM))[0] == 201
        assert (await call(None, ("127.0.0.1", port), "DELETE", "/services/cam-1"))[0] == 403


# -- event streams: no one client takes them all ----------------------------------------------


class Stream:
    """An open GET /events stream (its status, and the error when refused)."""

    def __init__(self, sock: socket.socket) -> None:
        self.conn = http.client.HTTPConnection("localhost", timeout=5)
        self.conn.sock = sock
        self.conn.request("GET", "/events", headers={"Accept": "text/event-stream"})
        self.resp = self.conn.getresponse()
        self.status = self.resp.status
        self.error = json.loads(self.resp.read())["error"] if self.status != 200 else None

    def close(self) -> None:
        self.resp.close()  # (it holds the socket: a "Connection: close" answer is its own)
        self.conn.close()


@pytest.fixture
def streams() -> Iterator[list[Stream]]:
    opened: list[Stream] = []
    yield opened
    for s in opened:
        s.close()


@pytest.mark.parametrize("door", ["unix", "tcp"])
@aio
async def test_one_client_cannot_take_every_event_stream(
    cfg: Config, store: Store, streams: list[Stream], door: str
) -> None:
    need_root()
    async with served(cfg, store) as (port, path):
        where: str | tuple[str, int] = str(path) if door == "unix" else ("127.0.0.1", port)

        def open_as(uid: int | None) -> Stream:
            s = Stream(as_user(uid, where))
            streams.append(s)
            return s

        got = []
        for _ in range(STREAMS_MAX):
            s = await asyncio.to_thread(open_as, USER_A)
            got.append(s.status)
            if s.status != 200:
                break
        refused = streams[-1]
        assert refused.status == 429, got
        held = got.count(200)
        assert 1 <= held <= STREAMS_MAX // 4, got
        assert refused.error is not None and f"uid {USER_A}" in refused.error, refused.error
        assert f"{held} event streams" in refused.error and "per client" in refused.error
        # Other users still get theirs.
        assert (await asyncio.to_thread(open_as, USER_B)).status == 200
        assert (await asyncio.to_thread(open_as, None)).status == 200
        # A stream its client closed frees its place at once (not at the next keep-alive).
        streams[0].close()
        for _ in range(50):
            await asyncio.sleep(0.05)
            s = await asyncio.to_thread(open_as, USER_A)
            if s.status == 200:
                break
        assert s.status == 200


# -- the clients remember their token -------------------------------------------------------------


# (`layer`: the API layer as a process, tests/unit/sdfr/conftest.py.)


def test_the_cli_remembers_its_token(
    layer: ApiLayer,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """`sdfr publish` then `sdfr unpublish`, two runs: the token is kept in the user's state
    (XDG_STATE_HOME), private; another user's runs (another state) may not unpublish."""
    alice, bob = tmp_path / "alice", tmp_path / "bob"
    monkeypatch.setenv("XDG_STATE_HOME", str(alice))
    assert sdfr(["--api", layer.api, "publish", "cam", "camera/rgb", "--ttl", "60"]) == 0
    sid = capsys.readouterr().out.strip()
    kept = alice / "sdfr-cli" / "owner-token"
    assert kept.stat().st_mode & 0o777 == 0o600 and kept.read_text().strip() not in sid
    monkeypatch.setenv("XDG_STATE_HOME", str(bob))
    for argv in (["unpublish", sid], ["renew", sid]):
        assert sdfr(["--api", layer.api, *argv]) == 1
        err = capsys.readouterr().err
        assert "belongs to the program that published it" in err and len(err.splitlines()) == 1
    monkeypatch.setenv("XDG_STATE_HOME", str(alice))
    assert sdfr(["--api", layer.api, "renew", sid]) == 0
    assert sdfr(["--api", layer.api, "unpublish", sid]) == 0
    capsys.readouterr()
    # On the unix socket a user's services are theirs whatever the token (root's: anyone's).
    assert sdfr(["--socket", str(layer.socket), "publish", "cam", "camera/rgb"]) == 0
    sid = capsys.readouterr().out.strip()
    monkeypatch.setenv("XDG_STATE_HOME", str(bob))
    assert sdfr(["--socket", str(layer.socket), "unpublish", sid]) == 0


def test_a_restarted_ros_bridge_still_owns_what_it_published(
    layer: ApiLayer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The ROS node publishes under ids derived from each message, and publishes them again
    after a respawn: it keeps the user's token (as `sdfr` does), so they stay its own."""
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path))
    request = ServiceRequest(name="front", type="sensor.camera")
    params = NodeParams(api=layer.api, spawn=False)
    first = Bridge(params, Recorder())
    try:
        sid = first.publish(request)
    finally:
        first.close()
    again = Bridge(params, Recorder())  # the node respawned
    try:
        assert again.publish(request) == sid  # the same message again: still its own
        assert again.unpublish(request) == sid
    finally:
        again.close()
