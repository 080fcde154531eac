"""Both Python clients (`sdfr.client.Client`, `sdfr.aio.AsyncClient`) against the API layer as
a real process: one suite, each test run with each client (`connect`, tests/support/clients.py);
then what only one of them has (the asyncio syntax), what both are made of, and what
importing them loads."""

from __future__ import annotations

import asyncio
import inspect
import subprocess
import sys
import threading
import time
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from sdfr.aio import AsyncClient
from sdfr.client import Client, calls, core
from sdfr.client.calls import Change
from sdfr.errors import ApiError
from sdfr.records import schema
from tests.support.api import ApiLayer, aio, free_port
from tests.support.clients import connect
from tests.unit.sdfr.test_client_cli import save_fleet

__all__ = ["connect"]  # (the fixture, for pytest)

OWNER = "X-SDFR-Owner"
Connect = Callable[..., Any]


def test_the_calls_over_tcp_and_the_unix_socket(layer: ApiLayer, connect: Connect) -> None:
    save_fleet(layer.state_dir)
    with connect(layer.api) as tcp, connect(unix_socket=layer.socket) as unix:
        sid = tcp.publish("arm", "manipulator", url="ros://arm", attributes={"dof": 6})
        assert [s["id"] for s in unix.services()] == [sid]
        assert unix.services()[0]["attributes"] == {"dof": 6}
        assert tcp.service(sid)["service"]["attributes"] == {"dof": 6}

        for client in (tcp, unix):
            assert [n["robot_id"] for n in client.neighbors()] == ["atlas", "bee"]
            assert len(client.neighbors(include_unreachable=True)) == 3
            assert [h["robot_id"] for h in client.history()] == ["atlas", "bee", "gone"]
            found = client.search("camera/rgb", fps=30)
            assert [(n["robot_id"], [s["id"] for s in n["services"]]) for n in found] == [
                ("atlas", ["c1"])
            ]
            assert [n["robot_id"] for n in client.search(attrs={"frame-rate": 30})] == ["atlas"]
            assert [n["robot_id"] for n in client.search("lidar")] == ["atlas"]
            me = client.self_info()
            assert me["robot_id"] == "r1" and me["discovery"]["up"] is False
            health = client.health()  # 503: the body all the same
            assert health["status"] == "degraded" and health["api"] == "up"
            assert "sdfr_local_services 1" in client.metrics()

        with pytest.raises(ApiError) as err:
            tcp.publish("", "manipulator")
        assert (err.value.status, err.value.field) == (422, "name")
        with pytest.raises(ApiError) as err:
            unix.request("GET", "/neighbors?x=1")
        assert (err.value.status, err.value.field) == (422, "x")

        unix.unpublish(sid)
        assert tcp.services() == []
        with pytest.raises(ApiError) as err:
            tcp.unpublish(sid)
        assert err.value.status == 404
        with pytest.raises(ApiError) as err:
            tcp.renew(sid)
        assert err.value.status == 404


def test_an_unreachable_daemon_says_what_to_check(tmp_path: Path, connect: Connect) -> None:
    port = free_port()
    with connect(f"127.0.0.1:{port}", retry_delays=()) as client, pytest.raises(ApiError) as err:
        client.services()
    assert err.value.status == 0 and isinstance(err.value, calls.Unreachable)
    assert str(err.value).startswith(f"cannot reach sdfrd at 127.0.0.1:{port}: ")
    assert "is sdfrd running" in err.value.message
    with connect(unix_socket=tmp_path / "api.sock") as client, pytest.raises(ApiError) as err:
        client.health()
    assert err.value.status == 0
    assert str(tmp_path / "api.sock") in str(err.value)


def test_a_publish_whose_answer_was_lost_is_sent_again_and_stored_once(
    layer: ApiLayer, connect: Connect
) -> None:
    with connect(layer.api) as client:
        sid = client.publish("lidar", "sensor.lidar")
        assert [s["id"] for s in client.services()] == [sid]  # the client chose the id
        # The same publish again (its answer lost, sdfrd restarted meanwhile): stored once.
        layer.kill()
        layer.start()
        again = client.publish_service("lidar", "sensor.lidar", service_id=sid)
        assert again["id"] == sid and len(client.services()) == 1
        with pytest.raises(ApiError) as err:
            client.publish("another", "sensor.lidar", service_id=sid)
        assert err.value.status == 409 and err.value.field == "id"


def test_a_publish_waits_a_moment_for_sdfrd(
    tmp_path_factory: pytest.TempPathFactory, connect: Connect
) -> None:
    """sdfrd is not answering when the publish starts (restarting): the client tries again."""
    api = ApiLayer(tmp_path_factory.mktemp("late"))
    started = threading.Timer(0.05, api.start)
    with connect(unix_socket=api.socket, timeout=2.0, retry_delays=(0.5, 1, 2, 4, 8)) as client:
        started.start()
        try:
            sid = client.publish("arm", "manipulator")
            assert [s["id"] for s in client.services()] == [sid]
        finally:
            started.join()
            api.stop()


def test_a_lease_is_published_when_made_kept_and_published_again(
    layer: ApiLayer, connect: Connect
) -> None:
    with connect(layer.api) as c, connect(layer.api) as other:
        with c.lease("gripper", "actuator/gripper", ttl=1.0) as kept:
            assert kept.id in {s["id"] for s in c.services()}  # published when made
            with pytest.raises(ApiError) as err:
                other.unpublish(kept.id)  # the lease's, with its client's token
            assert err.value.status == 403 and err.value.field == OWNER
            # Withdrawn behind its back (as if sdfrd was down past the ttl): published again.
            c.unpublish(kept.id)
            time.sleep(0.8)
            assert kept.id in {s["id"] for s in c.services()}
            time.sleep(0.8)
            assert kept.error is None and kept.renewals >= 2
        assert kept.id not in {s["id"] for s in c.services()}
        with pytest.raises(ApiError):  # a publish that fails raises when the lease is made
            c.lease("", "actuator/gripper", ttl=1.0)
        assert c.services() == []


def test_each_client_is_a_program_of_its_own(layer: ApiLayer, connect: Connect) -> None:
    with connect(layer.api) as mine, connect(layer.api) as other:
        sid = mine.publish("arm", "manipulator", ttl=30)
        assert other.service(sid)["id"] == sid  # anyone may read it
        for attempt in (lambda: other.unpublish(sid), lambda: other.renew(sid)):
            with pytest.raises(ApiError) as err:
                attempt()
            assert err.value.status == 403 and err.value.field == OWNER
        mine.renew(sid)
        # A program that keeps its token (e.g. in a file) is the owner again after a restart.
        with connect(layer.api, owner_token=mine.owner_token) as again:
            again.unpublish(sid)
        assert mine.services() == []


def test_watch_follows_and_resumes_after_a_restart(tmp_path: Path, connect: Connect) -> None:
    api = ApiLayer(tmp_path)
    api.start()
    seen: list[Change] = []
    opened = threading.Event()
    try:
        with connect(api.api) as c:
            start = c.events(since=None)["last_id"]

            def watch() -> None:
                with connect(api.api) as w:
                    for change in w.watch(["service"], since=start, on_open=opened.set):
                        seen.append(change)
                        if len(seen) == 3:
                            return

            t = threading.Thread(target=watch, daemon=True)
            t.start()
            sid = c.publish("cam", "camera/rgb")
            deadline = time.monotonic() + 5
            while not seen and time.monotonic() < deadline:
                time.sleep(0.05)
            api.stop()  # the stream breaks; the watcher reconnects
            opened.clear()
            api.start()
            c.close()
            c.unpublish(sid)
            c.publish("cam", "camera/rgb", service_id=sid)
            t.join(15)
            assert opened.is_set()
        assert [e.event for e in seen] == [
            "service.published",
            "service.unpublished",
            "service.published",
        ]
        assert seen[0].data["service_id"] == sid and seen[0].robot_id is None
        assert seen[0].id < seen[1].id < seen[2].id
    finally:
        api.stop()


# -- the asyncio syntax --------------------------------------------------------------------------


@aio
async def test_async_for_async_with_and_an_awaited_lease(layer: ApiLayer) -> None:
    async with AsyncClient(layer.api) as sdfr:
        start = (await sdfr.events(since=None))["last_id"]
        seen: list[Change] = []

        async def watch() -> None:
            async for change in sdfr.watch(["service"], since=start):
                seen.append(change)
                if len(seen) == 4:
                    return

        watcher = asyncio.create_task(watch())
        async with sdfr.lease("arm", "actuator/arm", ttl=1.0) as kept:
            await asyncio.sleep(1.5)  # past its ttl: renewed by the task
            assert kept.renewals >= 2 and kept.error is None
        kept = await sdfr.lease("arm", "actuator/arm", ttl=30)  # published when awaited
        assert kept.id in {s["id"] for s in await sdfr.services()}
        await kept.close()
        await asyncio.wait_for(watcher, 10)
        assert [c.event for c in seen] == [
            "service.published",
            "service.unpublished",
            "service.published",
            "service.unpublished",
        ]


# -- what both are made of -------------------------------------------------------------------------


def test_both_clients_are_the_one_api_with_the_same_construction() -> None:
    def public(cls: type) -> set[str]:
        return {n for n in dir(cls) if not n.startswith("_")}

    assert issubclass(Client, core.Api) and issubclass(AsyncClient, core.Api)
    assert public(Client) == public(AsyncClient)
    assert inspect.signature(Client) == inspect.signature(AsyncClient)
    assert inspect.iscoroutinefunction(AsyncClient.call)
    # Each method has the signature and the docstring of its call's definition.
    sig = inspect.signature(Client(retry_delays=()).publish)
    assert list(sig.parameters) == ["name", "type", "url", "attributes", "service_id", "ttl"]
    assert "ok" in (Client.health.__doc__ or "")


def test_the_health_documentation_follows_the_schema() -> None:
    """`health`'s docstring names every value the schema's status fields may have."""
    doc = calls.health.__doc__ or ""
    for name in ("status", "discovery", "state"):
        (literal,) = [
            a for a in typing.get_args(schema.Health.__annotations__[name]) if typing.get_args(a)
        ] or [schema.Health.__annotations__[name]]
        for value in typing.get_args(literal):
            assert f'"{value}"' in doc, (name, value)


def test_the_answers_are_typed_as_the_schema_records() -> None:
    hints = typing.get_type_hints(calls.health, include_extras=True)
    (answer,) = typing.get_args(hints["return"])
    assert typing.get_args(answer)[1] is schema.Health
    hints = typing.get_type_hints(calls.neighbors, include_extras=True)
    (answer,) = typing.get_args(hints["return"])
    (item,) = typing.get_args(answer)
    assert typing.get_args(item)[1] is schema.Neighbor


@pytest.mark.parametrize("module", ["sdfr.client", "sdfr.ros.core"])
def test_importing_the_client_loads_neither_the_daemon_nor_aiohttp(module: str) -> None:
    """The client, and the ROS bridge made of it, speak HTTP without sdfrd's code."""
    out = subprocess.run(
        [sys.executable, "-X", "importtime", "-c", f"import {module}"],
        capture_output=True,
        text=True,
        check=True,
    )
    loaded = {line.rpartition("|")[2].strip() for line in out.stderr.splitlines()}
    assert module in loaded
    for heavy in ("sdfr.wire", "sdfr.protocol", "sdfr.config.load", "sdfr.daemon", "aiohttp"):
        assert not {m for m in loaded if m == heavy or m.startswith(heavy + ".")}, heavy


def test_the_async_client_without_aiohttp_names_the_extra() -> None:
    code = "import sys; sys.modules['aiohttp'] = None; import sdfr.aio"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode != 0
    assert "pip install 'sdfr-robots[aio]'" in out.stderr.splitlines()[-1]
