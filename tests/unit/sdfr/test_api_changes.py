"""Leases, GET /services/{id}, GET /events, refused control characters, search by value and
the metrics, through the API in-process (and as a real process, for a restart)."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import time
from pathlib import Path
from typing import Any

import pytest
from aiohttp import ClientSession

from sdfr.api import HEARTBEAT_STALE, STATE, create_app
from sdfr.api.state import COUNTERS_FRESH, LIVENESS_WAIT, STATUS_WAIT
from sdfr.config.load import Config
from sdfr.records.events import Event
from sdfr.records.model import Service
from sdfr.store import EVENT_LOG_MAX, Store
from tests.support.api import ApiLayer, aio, serve, status
from tests.unit.sdfr.test_api import FLEET, peer

Client = ClientSession
SSE = {"Accept": "text/event-stream"}


async def publish(c: Client, **body: Any) -> dict[str, Any]:
    r = await c.post("/services", json={"name": "cam", "type": "camera/rgb", **body})
    assert r.status in (200, 201), await r.text()
    answer: dict[str, Any] = await r.json()
    return answer


@aio
async def test_a_lease_is_renewed_and_runs_out(cfg: Config, store: Store) -> None:
    async with serve(create_app(cfg, store)) as c:
        made = await publish(c, ttl=1.0)
        assert made["ttl"] == 1.0 and abs(made["expires"] - (time.time() + 1.0)) < 0.5
        sid = made["id"]
        r = await c.get(f"/services/{sid}")
        assert (await r.json())["expires"] == made["expires"]
        for _ in range(3):  # renewed every 0.5 s, it outlives its ttl
            await asyncio.sleep(0.5)
            r = await c.post(f"/services/{sid}/renew")
            assert r.status == 200, await r.text()
        listed = (await (await c.get("/services")).json())["services"]
        assert [(s["id"], s["ttl"]) for s in listed] == [(sid, 1.0)]
        await asyncio.sleep(1.4)  # no renewal: withdrawn like an unpublish
        assert (await (await c.get("/services")).json()) == {"services": [], "version": 2}
        r = await c.post(f"/services/{sid}/renew")
        assert r.status == 404 and "lease ran out" in (await r.json())["error"]
        page = await (await c.get("/events?since=0")).json()
        assert [e["event"] for e in page["events"]] == ["service.published", "service.expired"]


@aio
async def test_a_registration_without_ttl_lives_and_cannot_be_renewed(
    cfg: Config, store: Store
) -> None:
    async with serve(create_app(cfg, store)) as c:
        made = await publish(c)
        assert made["ttl"] is None and made["expires"] is None
        r = await c.post(f"/services/{made['id']}/renew")
        assert r.status == 409 and (await r.json())["field"] == "ttl"
        # Publishing it again with a ttl (the same id: a retry) makes it a lease.
        again = await publish(c, id=made["id"], ttl=60)
        assert again["ttl"] == 60.0 and again["version"] == made["version"]
        r = await c.post(f"/services/{made['id']}/renew", json={"ttl": 5})
        assert (await r.json())["ttl"] == 5.0


@pytest.mark.parametrize("ttl", [0, 0.5, -1, True, "10", 1e12, [1]])
@aio
async def test_a_bad_ttl_is_refused(cfg: Config, store: Store, ttl: object) -> None:
    async with serve(create_app(cfg, store)) as c:
        r = await c.post("/services", json={"name": "cam", "type": "t", "ttl": ttl})
        assert r.status == 422
        assert (await r.json())["field"] == "ttl"


def test_a_lease_that_ran_out_while_the_api_layer_was_down_ends_at_its_start(
    tmp_path: Path,
) -> None:
    layer = ApiLayer(tmp_path)
    layer.start()
    try:
        from sdfr.client import Client as Sync

        with Sync(layer.api) as c:
            sid = c.publish("arm", "actuator/arm", ttl=1.0)
            keep = c.publish("map", "map")
        layer.kill()  # no goodbye: the lease is on disk
        time.sleep(1.5)
        layer.start()
        with Sync(layer.api) as c:
            assert [s["id"] for s in c.services()] == [keep]
            assert [e.event for e in c.events(0)["events"]][-1] == "service.expired"
            assert sid not in {s["id"] for s in c.services()}
    finally:
        layer.stop()


@pytest.mark.parametrize(
    "body, field",
    [
        ({"name": "cam\nINFO forged line", "type": "t"}, "name"),
        ({"name": "cam\x1b[31m", "type": "t"}, "name"),
        ({"name": "cam", "type": "t", "url": "rtsp://x\r\n"}, "url"),
        ({"name": "cam", "type": "t", "attributes": {"k\x00": 1}}, "attributes.k\x00"),
        ({"name": "cam", "type": "t", "attributes": {"k": "a\u2028b"}}, "attributes.k"),
        ({"name": "cam\x85", "type": "t"}, "name"),
    ],
)
@aio
async def test_control_characters_are_refused(
    cfg: Config, store: Store, body: dict[str, Any], field: str
) -> None:
    async with serve(create_app(cfg, store)) as c:
        r = await c.post("/services", json=body)
        assert r.status == 422, await r.text()
        answer = await r.json()
        assert answer["field"] == field and "control characters" in answer["error"]


@aio
async def test_search_compares_numbers_and_booleans_by_value(
    cfg: Config, store: Store, discovery_store: Store
) -> None:
    robot = peer(
        "delta",
        True,
        Service("d1", "cam", "camera", None, {"fps": 30.0, "color": True, "model": "30"}),
    )
    discovery_store.save_peers([*FLEET, robot])
    async with serve(create_app(cfg, store)) as c:

        async def found(query: str) -> list[str]:
            r = await c.get(f"/neighbors/search?{query}")
            assert r.status == 200, await r.text()
            return [n["robot_id"] for n in (await r.json())["neighbors"]]

        assert await found("type=camera&attr.fps=30") == ["delta"]  # 30 finds 30.0
        assert await found("type=camera&attr.fps=3e1") == ["delta"]
        assert await found("type=camera/rgb&attr.fps=30.0") == ["alpha"]  # 30.0 finds 30
        assert await found("attr.color=True") == ["alpha", "delta"]
        assert await found("attr.color=1") == []  # a boolean is not a number
        assert await found("attr.model=30") == ["delta"]  # text by its text
        assert await found("attr.model=30.0") == []
        assert await found("attr.range=40.50") == ["alpha"]


async def read_events(resp: Any, n: int) -> list[tuple[str, str, dict[str, Any]]]:
    """The next `n` events of an SSE stream: (id, event, data)."""
    out: list[tuple[str, str, dict[str, Any]]] = []
    fields: dict[str, str] = {}
    while len(out) < n:
        line = (await asyncio.wait_for(resp.content.readline(), 5)).decode().rstrip("\n")
        if line == "":
            if "data" in fields:
                out.append((fields["id"], fields["event"], json.loads(fields["data"])))
            fields = {}
        elif not line.startswith(":"):
            key, _, value = line.partition(": ")
            fields[key] = value
    return out


@aio
async def test_events_stream_local_and_robot_changes_and_resume(
    cfg: Config, store: Store, discovery_store: Store
) -> None:
    async with serve(create_app(cfg, store)) as c:
        resp = await c.get("/events", headers=SSE)
        assert resp.headers["Content-Type"] == "text/event-stream; charset=utf-8"
        made = await publish(c, ttl=30)
        # The discovery layer's changes reach the stream through the store (the datagram
        # that wakes the hub is not sent here: the 1 s poll finds them).
        discovery_store.save_peers(
            [peer("alpha", True)], [Event("robot.appeared", "alpha", {"new": True})]
        )
        got = await read_events(resp, 2)
        assert [e[1] for e in got] == ["service.published", "robot.appeared"]
        assert got[0][2]["service_id"] == made["id"] and got[1][2]["robot_id"] == "alpha"
        assert int(got[0][0]) < int(got[1][0])
        resp.close()
        # Resume after the first: the second again, then the next change.
        resp = await c.get("/events", headers={**SSE, "Last-Event-ID": got[0][0]})
        await c.delete(f"/services/{made['id']}")
        again = await read_events(resp, 2)
        assert [e[1] for e in again] == ["robot.appeared", "service.unpublished"]
        resp.close()
        # Only some kinds.
        resp = await c.get("/events?since=0&event=robot", headers=SSE)
        assert [e[1] for e in await read_events(resp, 1)] == ["robot.appeared"]
        resp.close()


@aio
async def test_a_reader_too_far_behind_is_told_to_resync(
    cfg: Config, store: Store, discovery_store: Store
) -> None:
    discovery_store.save_peers([], [Event("robot.left", "x")])
    old = discovery_store.last_event_id()
    discovery_store.save_peers([], [Event("robot.indicator", "x")] * (EVENT_LOG_MAX + 1))
    async with serve(create_app(cfg, store)) as c:
        resp = await c.get("/events", headers={**SSE, "Last-Event-ID": str(old)})
        [(eid, kind, data)] = await read_events(resp, 1)
        assert kind == "resync" and data["after"] == old
        assert int(eid) == discovery_store.last_event_id()
        resp.close()
        page = await (await c.get(f"/events?since={old}")).json()
        assert page["events"][0]["event"] == "resync"
        r = await c.get("/events?since=x")
        assert r.status == 422 and (await r.json())["field"] == "since"
        r = await c.get("/events?event=robots")
        assert r.status == 422 and "no event kind" in (await r.json())["error"]


@aio
async def test_hold_renews_while_the_connection_is_open(cfg: Config, store: Store) -> None:
    async with serve(create_app(cfg, store)) as c:
        made = await publish(c, ttl=1.0)
        r = await c.post(f"/services/{made['id']}/hold")  # not a stream: one renewal
        assert r.status == 200 and (await r.json())["ttl"] == 1.0
        resp = await c.post(f"/services/{made['id']}/hold", headers=SSE)
        renewed = await read_events_named(resp, 4)
        assert len(renewed) == 4  # 4 renewals, about 1.3 s: past the ttl
        assert (await c.get(f"/services/{made['id']}")).status == 200
        resp.close()
        await asyncio.sleep(1.6)  # the holder is gone: the lease runs out
        assert (await c.get(f"/services/{made['id']}")).status == 404


async def read_events_named(resp: Any, n: int) -> list[str]:
    names: list[str] = []
    while len(names) < n:
        line = (await asyncio.wait_for(resp.content.readline(), 5)).decode()
        if line.startswith("event: renewed"):
            names.append(line)
    return names


@aio
async def test_metrics_build_process_and_peers(
    cfg: Config, store: Store, discovery_store: Store
) -> None:
    discovery_store.save_peers(FLEET)
    app = create_app(cfg, store)
    async with serve(app) as c:
        # The discovery layer's status: a process of its own (here the test's parent: alive)...
        other = status(heartbeat=time.time(), pid=os.getppid())
        app[STATE].take_status(json.dumps(other).encode())
        await c.get("/health")
        r = await c.get("/metrics")
        assert r.headers["Content-Type"] == "text/plain; version=0.0.4; charset=utf-8"
        text = await r.text()
        # ... or a thread of this process (--layers threads): its process once, as both.
        app[STATE].take_status(json.dumps(status(heartbeat=time.time())).encode())
        await asyncio.sleep(COUNTERS_FRESH)
        one = await (await c.get("/metrics")).text()
    assert 'process_open_fds{layer="both"}' in one and 'layer="api"' not in one
    assert 'sdfr_build_info{version="' in text and 'distribution="sdfr-robots"' in text
    assert 'sdfr_peer_indicator{robot_id="alpha"} 0.9' in text
    assert 'sdfr_peer_rtt_seconds{robot_id="alpha"} 0.00125' in text
    assert "charlie" not in text  # unreachable robots have no gauges
    for name in ("process_cpu_seconds_total", "process_resident_memory_bytes", "process_open_fds"):
        assert f'{name}{{layer="api"}}' in text and f'{name}{{layer="discovery"}}' in text
    assert "sdfr_api_request_duration_seconds_count" in text


@aio
async def test_an_answer_asks_the_discovery_layer_for_its_status_when_the_last_is_old(
    cfg: Config, store: Store
) -> None:
    """The discovery layer sends its status only when it changed, or when asked: an answer
    that shows it asks first (once COUNTERS_FRESH has passed), and waits for it, longer when
    the status it has would say "down"; with no discovery layer listening it does not wait."""
    state = create_app(cfg, store)[STATE]
    stale = time.time() - HEARTBEAT_STALE - 1
    state.take_status(json.dumps(status(heartbeat=stale, peers_known=9)).encode())
    assert not state.discovery().up
    started = time.monotonic()
    await state.fresh_status()  # nobody on discovery.sock: no wait
    assert time.monotonic() - started < STATUS_WAIT

    listener = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    listener.bind(str(cfg.state_dir / "discovery.sock"))
    listener.setblocking(False)
    asked: list[bytes] = []

    def answer() -> None:  # the discovery layer: its status now
        asked.append(listener.recv(64))
        state.take_status(json.dumps(status(heartbeat=time.time(), peers_known=4)).encode())

    loop = asyncio.get_running_loop()
    loop.add_reader(listener.fileno(), answer)
    try:
        await asyncio.sleep(COUNTERS_FRESH)
        await state.fresh_status()
        assert asked == [b"status\n"]
        now = state.discovery()
        assert now.up and now.heartbeat_age is not None and now.heartbeat_age < 1.0
        assert now.status is not None and now.status.peers_known == 4
        await state.fresh_status()  # fresh: not asked again
        assert asked == [b"status\n"]
    finally:
        loop.remove_reader(listener.fileno())

    try:
        # A discovery layer that does not answer (hung, stopped): the last status stays.
        await asyncio.sleep(COUNTERS_FRESH)
        started = time.monotonic()
        await state.fresh_status()
        took = time.monotonic() - started
        assert STATUS_WAIT <= took < LIVENESS_WAIT  # what it has says "up": a short wait
        assert state.discovery().up and listener.recv(64) == b"status\n"
        state.take_status(json.dumps(status(heartbeat=stale, peers_known=9)).encode())
        await asyncio.sleep(COUNTERS_FRESH)
        started = time.monotonic()
        await state.fresh_status()
        assert time.monotonic() - started >= LIVENESS_WAIT  # "down" only after this wait
        assert not state.discovery().up
    finally:
        listener.close()
