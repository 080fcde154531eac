"""The asyncio client (sdfr.aio) against the real API layer process: the same calls as the
sync client, `async for change in client.watch()`, a lease kept by a task; and the parity of
the two clients' signatures (both are made of sdfr.calls)."""

from __future__ import annotations

import asyncio
import inspect
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from sdfr.aio import AsyncClient
from sdfr.calls import Change
from sdfr.client import Client
from sdfr.errors import ApiError
from tests.support.api import ApiLayer, aio


@pytest.fixture(scope="module")
def layer(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ApiLayer]:
    api = ApiLayer(tmp_path_factory.mktemp("aio"))
    api.start()
    yield api
    api.stop()


def public(cls: type) -> dict[str, inspect.Signature]:
    return {
        name: inspect.signature(member)
        for name, member in vars(cls).items()
        if callable(member) and not name.startswith("_") and name not in ("close",)
    }


def test_both_clients_offer_the_same_calls_with_the_same_parameters() -> None:
    sync, asyn = public(Client), public(AsyncClient)
    assert set(sync) == set(asyn)
    for name, sig in sync.items():
        assert list(sig.parameters) == list(asyn[name].parameters), name
        for p, q in zip(sig.parameters.values(), asyn[name].parameters.values(), strict=True):
            assert (p.kind, p.default) == (q.kind, q.default), f"{name}({p.name})"
        if name not in ("lease", "watch"):  # (a context manager, an iterator)
            assert inspect.iscoroutinefunction(getattr(AsyncClient, name)), name


@aio
async def test_calls_watch_and_lease(layer: ApiLayer) -> None:
    async with AsyncClient(layer.api) as sdfr:
        assert (await sdfr.health())["api"] == "up"
        start = (await sdfr.events(since=None))["last_id"]
        seen: list[Change] = []

        async def watch() -> None:
            async for change in sdfr.watch(["service"], since=start):
                seen.append(change)
                if len(seen) == 4:
                    return

        watcher = asyncio.create_task(watch())
        sid = await sdfr.publish("cam", "camera/rgb", attributes={"fps": 30})
        assert (await sdfr.service(sid))["service"]["attributes"] == {"fps": 30}
        async with sdfr.lease("arm", "actuator/arm", ttl=1.0) as kept:
            await asyncio.sleep(1.5)  # past its ttl: renewed by the task
            assert kept.renewals >= 2 and kept.error is None
            assert kept.id in {s["id"] for s in await sdfr.services()}
        assert kept.id not in {s["id"] for s in await sdfr.services()}
        await sdfr.unpublish(sid)
        await asyncio.wait_for(watcher, 10)
        assert [c.event for c in seen] == [
            "service.published",
            "service.published",
            "service.unpublished",
            "service.unpublished",
        ]
        assert seen[1].data["service_id"] == kept.id and seen[1].robot_id is None
        with pytest.raises(ApiError) as err:
            await sdfr.renew(sid)
        assert err.value.status == 404


@aio
async def test_unreachable_says_what_to_check() -> None:
    async with AsyncClient("127.0.0.1:1", retry_delays=()) as sdfr:
        with pytest.raises(ApiError) as err:
            await sdfr.neighbors()
    assert err.value.status == 0
    assert "cannot reach sdfrd at 127.0.0.1:1" in err.value.message
    assert "is sdfrd running" in err.value.message


def test_sync_watch_resumes_after_a_restart(tmp_path: Path) -> None:
    api = ApiLayer(tmp_path)
    api.start()
    seen: list[str] = []
    try:
        with Client(api.api) as c:
            start = c.events(since=None)["last_id"]

            def watch() -> None:
                with Client(api.api) as w:
                    for change in w.watch(since=start):
                        seen.append(change.event)
                        if len(seen) == 2:
                            return

            t = threading.Thread(target=watch, daemon=True)
            t.start()
            sid = c.publish("cam", "camera/rgb")
            deadline = time.monotonic() + 5
            while not seen and time.monotonic() < deadline:
                time.sleep(0.05)
            api.stop()  # the stream breaks; the watcher reconnects
            api.start()
            c.close()
            c.unpublish(sid)
            t.join(15)
        assert seen == ["service.published", "service.unpublished"]
    finally:
        api.stop()


def test_sync_lease_keeps_and_republishes(layer: ApiLayer) -> None:
    with Client(layer.api) as c:
        with c.lease("gripper", "actuator/gripper", ttl=1.0) as kept:
            # Withdrawn behind its back (as if sdfrd was down past the ttl): published again.
            c.unpublish(kept.id)
            time.sleep(0.8)
            assert kept.id in {s["id"] for s in c.services()}
            time.sleep(0.8)
            assert kept.error is None and kept.renewals >= 2
        assert kept.id not in {s["id"] for s in c.services()}


def test_the_clients_answer_types_match_the_api_models() -> None:
    """The TypedDicts of sdfr.calls name the fields of the API's own models (which the
    OpenAPI document, and schemathesis against the daemon, are made from)."""
    import msgspec

    from sdfr import calls
    from sdfr.api import models

    pairs = [
        (calls.ServiceJson, models.ServiceOutput),
        (calls.LocalServiceJson, models.LocalService),
        (calls.Published, models.Published),
        (calls.Renewed, models.Renewed),
        (calls.Neighbor, models.Neighbor),
        (calls.PeerJson, models.PeerJson),
        (calls.Health, models.Health),
    ]
    for typed, model in pairs:
        fields = {f.name for f in msgspec.structs.fields(model)}
        assert set(typed.__annotations__) | set(typed.__required_keys__) == fields, typed
