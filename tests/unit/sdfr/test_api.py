"""The REST API and the description server, in-process (aiohttp's test server, a temp store)."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import os
import re
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from aiohttp import ClientSession

from sdfr import wire
from sdfr.api import (
    HEARTBEAT_STALE,
    STATE,
    create_app,
    notify_discovery,
    openapi_document,
    pid_alive,
)
from sdfr.api.state import discovery_state
from sdfr.config.load import Config, location_max_len
from sdfr.protocol import auth
from sdfr.records.model import PeerRecord, Service
from sdfr.records.status import DiscoveryStatus
from sdfr.store import Store
from tests.support.api import aio, serve, status


def service(sid: str, stype: str, **attrs: Any) -> Service:
    return Service(id=sid, name=f"{stype} {sid}", type=stype, url=None, attributes=attrs)


def peer(robot_id: str, reachable: bool, *services: Service) -> PeerRecord:
    now = time.time()
    return PeerRecord(
        robot_id=robot_id,
        address=f"10.7.0.{len(robot_id)}",
        location=f"http://10.7.0.{len(robot_id)}:8701/description.json",
        boot_id=1,
        version=2,
        digest="d" * 16,
        reachable=reachable,
        first_seen=now - 60,
        last_seen=now - (0 if reachable else 45),
        indicator=0.9 if reachable else 0.0,
        rtt_ms=1.25 if reachable else None,
        pings=10,
        services=services,
    )


FLEET = [
    peer(
        "alpha",
        True,
        service("a1", "camera/rgb", fps=30, color=True),
        service("a2", "lidar", range=40.5),
    ),
    peer("bravo", True, service("b1", "camera/rgb", fps=15, color=False)),
    peer("charlie", False, service("c1", "camera/rgb", fps=30, color=True)),
]


# -- local registrations -----------------------------------------------------------------------


@aio
async def test_publish_list_unpublish(cfg: Config, store: Store) -> None:
    async with serve(create_app(cfg, store)) as c:
        body: dict[str, Any] = {"name": "front cam", "type": "camera/rgb", "url": "rtsp://x/1"}
        body["attributes"] = {"fps": 30, "hdr": True}
        r = await c.post("/services", json=body)
        assert r.status == 201
        assert r.headers["Content-Type"] == "application/json; charset=utf-8"
        created = await r.json()
        sid = created["id"]
        assert re.fullmatch(r"[0-9a-f]{12}", sid)
        assert r.headers["Location"] == f"/services/{sid}"
        assert created["service"] == {"id": sid, **body}
        assert created["version"] == 1

        r = await c.get("/services")
        listed = {**created["service"], "ttl": None, "expires": None}
        assert await r.json() == {"services": [listed], "version": 1}

        r = await c.delete(f"/services/{sid}")
        assert r.status == 204
        r = await c.get("/services")
        assert await r.json() == {"services": [], "version": 2}

        r = await c.delete(f"/services/{sid}")
        assert r.status == 404
        assert (await r.json())["field"] == "id"
    # Durable: a fresh connection (another process) sees the registrations' state.
    assert store.local_state() == (2, [])


BIG = {f"k{i}": "v" * 250 for i in range(10)}


@pytest.mark.parametrize(
    ("body", "status", "field"),
    [
        ({"type": "camera"}, 422, "name"),
        ({"name": "", "type": "camera"}, 422, "name"),
        ({"name": "x", "type": "has space"}, 422, "type"),
        ({"name": "x"}, 422, "type"),
        ({"name": "x", "type": "t", "attributes": [1, 2]}, 422, "attributes"),
        ({"name": "x", "type": "t", "attributes": {"a": {"b": 1}}}, 422, "attributes.a"),
        ({"name": "x", "type": "t", "colour": "red"}, 422, "colour"),
        ({"name": "x", "type": "t", "id": "has space"}, 422, "id"),
        ({"name": "x", "type": "t", "url": 5}, 422, "url"),
        ({"name": "x", "type": "t", "attributes": BIG}, 413, "service"),
        ([{"name": "x", "type": "t"}], 422, "body"),
        ("{not json", 400, None),
        ('{"name": "x", "type": "t", "attributes": {"a": NaN}}', 400, None),
        ("", 400, None),
    ],
)
@aio
async def test_publish_rejects_naming_the_field(
    cfg: Config, store: Store, body: Any, status: int, field: str | None
) -> None:
    async with serve(create_app(cfg, store)) as c:
        data = body if isinstance(body, str) else json.dumps(body)
        r = await c.post("/services", data=data, headers={"Content-Type": "application/json"})
        assert r.status == status
        answer = await r.json()
        assert answer["field"] == field
        assert isinstance(answer["error"], str) and answer["error"]
        assert store.local_state() == (0, [])


@aio
async def test_unknown_paths_and_methods_answer_json(cfg: Config, store: Store) -> None:
    async with serve(create_app(cfg, store)) as c:
        r = await c.get("/nope")
        assert r.status == 404
        assert r.content_type == "application/json"
        assert (await r.json())["field"] is None
        r = await c.put("/services")
        assert r.status == 405
        assert set(r.headers["Allow"].split(",")) == {"GET", "POST"}
        assert "PUT" in (await r.json())["error"]
        r = await c.post(
            "/services", data=b"x" * 100_000, headers={"Content-Type": "application/json"}
        )
        assert r.status == 413
        assert "error" in await r.json()


# -- neighbours, search, history ---------------------------------------------------------------


@aio
async def test_neighbors_are_the_reachable_robots(
    cfg: Config, store: Store, discovery_store: Store
) -> None:
    discovery_store.save_peers(FLEET)
    async with serve(create_app(cfg, store)) as c:
        r = await c.get("/neighbors")
        robots = (await r.json())["neighbors"]
        assert [n["robot_id"] for n in robots] == ["alpha", "bravo"]
        assert set(robots[0]) == {
            "robot_id",
            "address",
            "reachable",
            "indicator",
            "rtt_ms",
            "last_seen",
            "services",
        }
        assert robots[0]["services"][0] == FLEET[0].services[0].to_json()
        assert robots[0]["indicator"] == 0.9 and robots[0]["rtt_ms"] == 1.25

        r = await c.get("/neighbors", params={"all": "1"})
        robots = (await r.json())["neighbors"]
        assert [(n["robot_id"], n["reachable"]) for n in robots] == [
            ("alpha", True),
            ("bravo", True),
            ("charlie", False),
        ]
        for query, field in [({"all": "maybe"}, "all"), ({"since": "1"}, "since")]:
            r = await c.get("/neighbors", params=query)
            assert r.status == 422
            assert (await r.json())["field"] == field


async def _search(c: ClientSession, query: str) -> dict[str, list[str]]:
    r = await c.get("/neighbors/search?" + query)
    assert r.status == 200, await r.text()
    return {n["robot_id"]: [s["id"] for s in n["services"]] for n in (await r.json())["neighbors"]}


@aio
async def test_search_by_type_and_attributes(
    cfg: Config, store: Store, discovery_store: Store
) -> None:
    discovery_store.save_peers(FLEET)
    async with serve(create_app(cfg, store)) as c:
        # Only reachable robots, each with only its matching services.
        assert await _search(c, "type=camera/rgb") == {"alpha": ["a1"], "bravo": ["b1"]}
        assert await _search(c, "type=lidar") == {"alpha": ["a2"]}
        assert await _search(c, "attr.fps=30") == {"alpha": ["a1"]}
        assert await _search(c, "attr.color=false") == {"bravo": ["b1"]}
        assert await _search(c, "attr.range=40.5") == {"alpha": ["a2"]}
        assert await _search(c, "type=camera/rgb&attr.fps=15&attr.color=false") == {"bravo": ["b1"]}
        assert await _search(c, "type=camera/rgb&attr.fps=60") == {}
        assert await _search(c, "type=nothing") == {}


@pytest.mark.parametrize(
    ("query", "field"),
    [
        ("", "type"),
        ("type=", "type"),
        ("type=a&type=b", "type"),
        ("kind=camera", "kind"),
        ("type=camera&attr.=1", "attr."),
        ("attr.fps=1&attr.fps=2", "attr.fps"),
    ],
)
@aio
async def test_search_rejects_bad_queries(
    cfg: Config, store: Store, query: str, field: str
) -> None:
    async with serve(create_app(cfg, store)) as c:
        r = await c.get("/neighbors/search?" + query)
        assert r.status == 422
        assert (await r.json())["field"] == field


@aio
async def test_history_lists_every_robot_ever_seen(
    cfg: Config, store: Store, discovery_store: Store
) -> None:
    discovery_store.save_peers(FLEET)
    async with serve(create_app(cfg, store)) as c:
        r = await c.get("/history")
        assert await r.json() == {"robots": [p.to_json() for p in FLEET]}


@aio
async def test_peer_cache_follows_the_other_connection(
    cfg: Config, store: Store, discovery_store: Store
) -> None:
    loads = 0
    load_peers = store.load_peers

    def counting() -> list[PeerRecord]:
        nonlocal loads
        loads += 1
        return load_peers()

    store.load_peers = counting  # type: ignore[method-assign]
    async with serve(create_app(cfg, store)) as c:
        discovery_store.save_peers(FLEET[:1])
        for _ in range(3):
            r = await c.get("/neighbors")
            assert [n["robot_id"] for n in (await r.json())["neighbors"]] == ["alpha"]
        await c.get("/history")
        assert loads == 1  # nothing changed: neither re-read nor re-serialised

        discovery_store.save_peers([FLEET[1], peer("alpha", False)])
        r = await c.get("/neighbors")
        assert [n["robot_id"] for n in (await r.json())["neighbors"]] == ["bravo"]
        assert loads == 2

        # A commit that leaves the peers alone (the status heartbeat) keeps the answers.
        discovery_store.write_status({"pid": os.getpid()})
        r = await c.get("/neighbors")
        assert [n["robot_id"] for n in (await r.json())["neighbors"]] == ["bravo"]


# -- this robot, health ------------------------------------------------------------------------


@aio
async def test_self_describes_this_robot(cfg: Config, store: Store, discovery_store: Store) -> None:
    async with serve(create_app(cfg, store)) as c:
        r = await c.get("/self")
        me = await r.json()
        assert me["robot_id"] == "r1" and me["fleet"] == 7 and me["address"] == ""
        assert me["discovery"]["up"] is False
        await c.post("/services", json={"name": "arm", "type": "manipulator"})
        discovery_store.write_status(status())
        r = await c.get("/self")
        me = await r.json()
        assert me["address"] == "10.7.3.4" and me["boot_id"] == 5 and me["version"] == 1
        assert me["location"] == "http://10.7.3.4:8701/description.json"
        assert [s["name"] for s in me["services"]] == ["arm"]
        assert me["discovery"]["up"] is True
        assert me["discovery"]["pid"] == os.getpid()


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


@aio
async def test_health_follows_the_discovery_heartbeat(
    cfg: Config, store: Store, discovery_store: Store
) -> None:
    async with serve(create_app(cfg, store)) as c:
        r = await c.get("/health")  # discovery never ran
        assert r.status == 503
        assert await r.json() == {
            "status": "degraded",
            "api": "up",
            "discovery": "down",
            "discovery_heartbeat_age": None,
            "discovery_error": None,
            "state": "ok",
            "state_error": None,
            "auth": None,
            "warnings": [],
        }

        discovery_store.write_status(status())
        r = await c.get("/health")
        assert r.status == 200
        answer = await r.json()
        assert answer["status"] == "ok" and answer["discovery"] == "up"
        assert 0 <= answer["discovery_heartbeat_age"] < 1

        discovery_store.write_status(status(pid=_dead_pid()))
        r = await c.get("/health")
        assert r.status == 503
        assert (await r.json())["discovery"] == "down"

        stale = {**status(), "heartbeat": time.time() - HEARTBEAT_STALE - 1}
        discovery_store.status_path.write_text(json.dumps(stale))
        r = await c.get("/health")
        assert r.status == 503
        assert (await r.json())["discovery_heartbeat_age"] > HEARTBEAT_STALE

        # Degraded, the API still answers from the last known state.
        r = await c.get("/self")
        assert (await r.json())["address"] == "10.7.3.4"


def test_a_discovery_layer_thread_that_ended_is_down_though_its_process_runs() -> None:
    """With --layers threads the status names the layer's thread: its process (this one) runs
    on after the thread ended, and the layer is down at once, not HEARTBEAT_STALE later."""
    tids: list[int] = []
    done = threading.Event()
    layer = threading.Thread(target=lambda: (tids.append(threading.get_native_id()), done.wait()))
    layer.start()
    while not tids:
        time.sleep(0.001)
    record = DiscoveryStatus.from_json({**status(), "heartbeat": time.time(), "thread": tids[0]})
    assert record is not None and record.thread == tids[0]
    assert discovery_state(record).up
    done.set()
    layer.join()
    # join() returns when the thread's Python code is done; the kernel removes the thread a
    # moment later (on a busy machine, milliseconds: CI saw it still there).
    task = Path(f"/proc/{os.getpid()}/task/{tids[0]}")
    deadline = time.monotonic() + 10
    while task.exists():
        assert time.monotonic() < deadline, f"{task} still there 10 s after the thread ended"
        time.sleep(0.001)
    assert not discovery_state(record).up
    assert discovery_state(dataclasses.replace(record, thread=None)).up  # (a process's status)


def test_pid_alive_treats_a_zombie_as_dead() -> None:
    assert pid_alive(os.getpid())
    zombie = subprocess.Popen([sys.executable, "-c", "pass"])
    try:
        deadline = time.monotonic() + 10
        while pid_alive(zombie.pid):  # exited but not reaped: a zombie
            assert time.monotonic() < deadline, "the child never became a zombie"
            time.sleep(0.01)
        os.kill(zombie.pid, 0)  # still in the process table
    finally:
        zombie.wait()
    assert not pid_alive(zombie.pid)
    assert not pid_alive(0)


# -- /metrics, /openapi.json -------------------------------------------------------------------

SAMPLE = re.compile(
    r'^(?P<name>[a-zA-Z_:][a-zA-Z0-9_:]*)(?:\{(?P<labels>(?:[a-z_]+="(?:[^"\\]|\\.)*",?)*)\})? '
    r"(?P<value>[-+0-9.eE]+|\+Inf|NaN)$"
)


def parse_metrics(text: str) -> dict[str, float]:
    """Every line is a HELP, a TYPE or a sample; samples keyed by name{labels}."""
    samples: dict[str, float] = {}
    typed: set[str] = set()
    for line in text.splitlines():
        if line.startswith("# HELP "):
            continue
        if line.startswith("# TYPE "):
            _, _, name, kind = line.split(" ", 3)
            assert kind in ("counter", "gauge", "histogram"), line
            typed.add(name)
            continue
        m = SAMPLE.match(line)
        assert m, f"not a sample: {line!r}"
        family = re.sub(r"_(bucket|sum|count)$", "", m["name"])
        assert m["name"] in typed or family in typed, f"no TYPE before {line!r}"
        key = m["name"] + (f"{{{m['labels']}}}" if m["labels"] else "")
        samples[key] = float(m["value"])
    return samples


@aio
async def test_metrics_exposition(cfg: Config, store: Store, discovery_store: Store) -> None:
    discovery_store.save_peers(FLEET)
    discovery_store.write_status(status())
    async with serve(create_app(cfg, store)) as c:
        await c.post("/services", json={"name": "arm", "type": "manipulator"})
        await c.get("/neighbors")
        r = await c.get("/metrics")
        assert r.status == 200
        assert r.headers["Content-Type"] == "text/plain; version=0.0.4; charset=utf-8"
        samples = parse_metrics(await r.text())
    assert samples['sdfr_datagrams_total{direction="in",type="alive"}'] == 7
    assert samples['sdfr_datagrams_total{direction="out",type="byebye"}'] == 0
    assert samples['sdfr_bytes_total{direction="out"}'] == 3100
    assert samples['sdfr_rejects_total{reason="bad-fleet"}'] == 2
    assert samples['sdfr_rejects_total{reason="odd\\"reason"}'] == 1
    assert samples['sdfr_peers{state="reachable"}'] == 2
    assert samples['sdfr_peers{state="known"}'] == 3
    assert samples["sdfr_local_services"] == 1
    assert samples["sdfr_discovery_up"] == 1
    labels = 'method="GET",route="/neighbors"'
    assert samples[f"sdfr_api_request_duration_seconds_count{{{labels}}}"] == 1
    assert samples[f'sdfr_api_request_duration_seconds_bucket{{{labels},le="+Inf"}}'] == 1
    assert samples[f"sdfr_api_request_duration_seconds_sum{{{labels}}}"] > 0
    assert 'sdfr_api_request_duration_seconds_count{method="POST",route="/services"}' in samples


@aio
async def test_openapi_documents_exactly_the_routes(cfg: Config, store: Store) -> None:
    app = create_app(cfg, store)
    routes = set(app.routes())
    doc = openapi_document()
    documented = {(m.upper(), path) for path, ops in doc["paths"].items() for m in ops}
    assert routes == documented
    assert doc["openapi"].startswith("3.1")

    # Every reference resolves, and every error answer is the error schema.
    def refs(node: Any) -> Iterator[str]:
        if isinstance(node, dict):
            if "$ref" in node:
                yield node["$ref"]
            for value in node.values():
                yield from refs(value)
        elif isinstance(node, list):
            for value in node:
                yield from refs(value)

    for ref in refs(doc):
        assert ref.removeprefix("#/components/schemas/") in doc["components"]["schemas"], ref
    for ops in doc["paths"].values():
        for op in ops.values():
            for code, answer in op["responses"].items():
                if code.startswith(("4", "5")) and code != "503":
                    schema = answer["content"]["application/json"]["schema"]
                    assert schema == {"$ref": "#/components/schemas/Error"}
    async with serve(app) as c:
        r = await c.get("/openapi.json")
        assert await r.json() == doc


# -- the description server, discovery notification --------------------------------------------


def test_notify_discovery_sends_a_datagram(tmp_path: Path) -> None:
    notify_discovery(tmp_path)  # nobody listening: silently nothing
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as listener:
        listener.bind(str(tmp_path / "discovery.sock"))
        listener.settimeout(5)
        notify_discovery(tmp_path)
        assert listener.recv(64) == b"services\n"
    notify_discovery(tmp_path)  # a socket file nobody reads any more: refused, ignored


@aio
async def test_publish_and_unpublish_wake_discovery(cfg: Config, store: Store) -> None:
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as listener:
        listener.bind(str(cfg.state_dir / "discovery.sock"))
        listener.setblocking(False)
        async with serve(create_app(cfg, store)) as c:
            r = await c.post("/services", json={"name": "arm", "type": "manipulator"})
            assert listener.recv(64) == b"services\n"
            await c.delete(f"/services/{(await r.json())['id']}")
            assert listener.recv(64) == b"services\n"
            await c.post("/services", json={"name": ""})  # rejected: nothing to announce
            with pytest.raises(BlockingIOError):
                listener.recv(64)


# -- what the fleet could never see ------------------------------------------------------------


@aio
async def test_a_publish_beyond_255_update_parts_is_refused(cfg: Config, store: Store) -> None:
    """Publish services of one size until refused: exactly as many as one announcement can
    carry are accepted, and the set really encodes in 255 parts with this robot's headers."""
    name = "n" * 100
    one = {"name": name, "type": "sensor.kind", "url": "http://10.0.0.1/" + "u" * 100}
    size = wire.service_json_size(Service.from_json(one, service_id="0" * 12))
    location_len = location_max_len(cfg.describe)
    expect = 1
    while wire.parts_needed([size] * (expect + 1), robot_id="r1", location_len=location_len) <= 255:
        expect += 1
    async with serve(create_app(cfg, store)) as c:
        for _ in range(expect):
            assert (await c.post("/services", json=one)).status == 201
        r = await c.post("/services", json=one)
        assert r.status == 507
        body = await r.json()
        assert body["field"] == "services" and "255" in body["error"] and "256" in body["error"]
    _, services = store.local_state()
    assert len(services) == expect
    origin = wire.Origin(255, "r1", 2**31 - 1, 2**53 - 1, "f" * 16)
    location = "http://" + "9" * (location_len - len("http://:1/description.json")) + ":1/"
    location = location.ljust(location_len, "x")
    parts = wire.encode_update_parts(origin, location, 86400, services)
    assert len(parts) <= 255


def body_of_json_size(size: int) -> dict[str, Any]:
    """A publish body whose service, with the 12-character id the API gives it, has `size`
    bytes of compact JSON."""
    body: dict[str, Any] = {"name": "n" * 100, "type": "t", "attributes": {"a": "", "b": ""}}
    pad = size - wire.service_json_size(Service.from_json(body, service_id="0" * 12))
    body["attributes"] = {"a": "x" * (pad // 2), "b": "y" * (pad - pad // 2)}
    assert wire.service_json_size(Service.from_json(body, service_id="0" * 12)) == size
    return body


def most_accepted(size: int, cfg: Config) -> int:
    """How many services of `size` bytes of JSON this robot's set may hold, by parts_needed."""
    location_len = location_max_len(cfg.describe)

    def fits(n: int) -> bool:
        needed = wire.parts_needed([size] * n, robot_id=cfg.robot_id, location_len=location_len)
        return needed <= wire.MAX_PARTS

    lo, hi = 1, 1
    while fits(hi):  # parts_needed grows with n: find the last n that fits
        lo, hi = hi, hi * 2
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if fits(mid) else (lo, mid)
    return lo


#: The longest headers any robot can send an Update with: a 64-character robot id, a
#: 200-byte LOCATION, the longest HOST (an IPv6 group, port 65535) and numbers.
WORST_ORIGIN = wire.Origin(255, "r" * 64, 2**31 - 1, 2**53 - 1, "f" * 16)
WORST_LOCATION = "http://" + "l" * (wire.MAX_LOCATION - len("http://"))
WORST_GROUP = "ffff:ffff:ffff:ffff:ffff:ffff:ffff:ffff"


@aio
async def test_services_of_the_largest_size_are_accepted_255_times(
    cfg: Config, store: Store
) -> None:
    size = wire.max_service_json_bytes()
    body = body_of_json_size(size)
    expect = most_accepted(size, cfg)
    assert expect == wire.MAX_PARTS  # each fills a datagram alone, whatever the headers
    async with serve(create_app(cfg, store)) as c:
        for _ in range(expect):
            r = await c.post("/services", json=body)
            assert r.status == 201, await r.text()
        r = await c.post("/services", json=body)
        assert r.status == 507
        answer = await r.json()
        assert answer["field"] == "services" and "255" in answer["error"]
    _, services = store.local_state()
    assert len(services) == wire.MAX_PARTS
    parts = wire.encode_update_parts(
        WORST_ORIGIN, WORST_LOCATION, 86400, services, group=WORST_GROUP, port=65535
    )
    assert len(parts) == wire.MAX_PARTS
    assert all(len(p) <= wire.MAX_ENCODED for p in parts)


@aio
async def test_concurrent_publishes_at_the_limit_never_overshoot(cfg: Config, store: Store) -> None:
    """On a slow disk the fsync runs in a thread and other publishes are checked meanwhile:
    the ones checked but not stored yet count too."""
    body = body_of_json_size(wire.max_service_json_bytes())
    app = create_app(cfg, store)
    async with serve(app) as c:
        for _ in range(wire.MAX_PARTS - 5):
            assert (await c.post("/services", json=body)).status == 201
        app[STATE].writer.fsync_avg = 10.0  # as measured on a slow disk: fsync in a thread
        answers = await asyncio.gather(*(c.post("/services", json=body) for _ in range(20)))
        assert sorted(r.status for r in answers) == [201] * 5 + [507] * 15
        # Nothing is left reserved: a removal makes room for exactly one more.
        sid = (await (await c.get("/services")).json())["services"][0]["id"]
        assert (await c.delete(f"/services/{sid}")).status == 204
        assert (await c.post("/services", json=body)).status == 201
        assert (await c.post("/services", json=body)).status == 507
    _, services = store.local_state()
    assert len(services) == wire.MAX_PARTS


@aio
async def test_thousands_of_small_services_are_accepted_up_to_the_limit(
    cfg: Config, store: Store
) -> None:
    body = {"name": "s", "type": "t"}
    size = wire.service_json_size(Service.from_json(body, service_id="0" * 12))
    expect = most_accepted(size, cfg)
    assert expect > 2000
    app = create_app(cfg, store)
    async with serve(app) as c:
        # Most of them in bursts, grouped into one transaction each (as on a slow disk), or
        # this takes a minute: every publish re-reads the local set.  The last 20 one by one.
        app[STATE].writer.fsync_avg = 10.0
        done = 0
        while done < expect - 20:
            burst = min(200, expect - 20 - done)
            answers = await asyncio.gather(*(c.post("/services", json=body) for _ in range(burst)))
            assert [r.status for r in answers] == [201] * burst
            done += burst
        app[STATE].writer.fsync_avg = 0.0
        for i in range(done, expect):
            r = await c.post("/services", json=body)
            assert r.status == 201, (i, await r.text())
        r = await c.post("/services", json=body)
        assert r.status == 507
        answer = await r.json()
        assert answer["field"] == "services" and "255" in answer["error"]
        r = await c.get("/services")
        assert len((await r.json())["services"]) == expect
    _, services = store.local_state()
    assert len(services) == expect
    # The set goes out in at most 255 parts with the longest headers this robot can have.
    origin = wire.Origin(255, "r1", 2**31 - 1, 2**53 - 1, "f" * 16)
    location = "http://255.255.255.255:8701/description.json"
    assert len(location) >= location_max_len(cfg.describe)
    parts = wire.encode_update_parts(
        origin, location, 86400, services, group=WORST_GROUP, port=65535
    )
    assert len(parts) <= wire.MAX_PARTS


# -- /health: failing and warnings --------------------------------------------------------------


@aio
async def test_health_says_why_discovery_fails_and_what_to_look_at(
    cfg: Config, store: Store, discovery_store: Store
) -> None:
    async with serve(create_app(cfg, store)) as c:
        discovery_store.write_status(status(errors={"recent": 1, "last": "timer failed: X"}))
        r = await c.get("/health")
        assert r.status == 200 and (await r.json())["discovery"] == "up"  # one failure: up
        discovery_store.write_status(status(errors={"recent": 3, "last": "timer failed: X"}))
        r = await c.get("/health")
        answer = await r.json()
        assert r.status == 503 and answer["discovery"] == "failing"
        assert answer["status"] == "degraded" and answer["discovery_error"] == "timer failed: X"
        too_big = "cannot announce the service set: 300 services need 256 update parts"
        discovery_store.write_status(status(errors={"recent": 0, "persistent": too_big}))
        r = await c.get("/health")
        assert r.status == 503 and (await r.json())["discovery_error"] == too_big

        conflict = {"address": "10.7.0.9", "boot_id": 77, "last_seen": time.time(), "count": 4}
        discovery_store.write_status(
            status(robot_id_conflict=conflict, auth={"mode": "sign", "received": {"ab": 3}})
        )
        r = await c.get("/health")
        answer = await r.json()
        assert r.status == 200 and answer["status"] == "warning" and answer["auth"] == "sign"
        assert any("10.7.0.9" in w and "boot 77" in w for w in answer["warnings"])
        assert any("mode sign" in w and "enforce" in w for w in answer["warnings"])
        text = await (await c.get("/metrics")).text()
        assert "sdfr_robot_id_conflicts_total 4" in text
        assert 'sdfr_auth_mode{mode="sign"} 1' in text
        assert 'sdfr_auth_verified_total{key="ab"} 3' in text


@aio
async def test_health_warns_while_unsigned_datagrams_are_accepted(
    cfg: Config, store: Store, discovery_store: Store
) -> None:
    async with serve(create_app(cfg, store)) as c:
        discovery_store.write_status(status(auth={"mode": "open", "received": {}}))
        answer = await (await c.get("/health")).json()
        assert (answer["status"], answer["auth"], answer["warnings"]) == ("ok", "open", [])
        assert answer["discovery_error"] is None
        discovery_store.write_status(status(auth={"mode": "accept", "received": {}}))
        r = await c.get("/health")
        answer = await r.json()
        assert r.status == 200 and answer["status"] == "warning" and answer["auth"] == "accept"
        assert answer["discovery"] == "up"
        [warning] = answer["warnings"]
        assert "mode accept" in warning and "sdfr keys mode enforce" in warning
        discovery_store.write_status(status(auth={"mode": "enforce", "received": {}}))
        answer = await (await c.get("/health")).json()
        assert answer["status"] == "ok" and answer["warnings"] == []
        # Failing beats a warning: a 503, and the warnings still say what else to look at.
        discovery_store.write_status(
            status(
                auth={"mode": "accept", "received": {}},
                errors={"recent": 5, "last": "send failed: ENETUNREACH"},
            )
        )
        r = await c.get("/health")
        answer = await r.json()
        assert r.status == 503 and answer["status"] == "degraded"
        assert answer["discovery"] == "failing"
        assert answer["discovery_error"] == "send failed: ENETUNREACH"
        # Down: no warnings from a status nobody keeps up to date.
        dead = status(auth={"mode": "accept", "received": {}}, pid=_dead_pid())
        discovery_store.write_status(dead)
        r = await c.get("/health")
        answer = await r.json()
        assert r.status == 503 and answer["discovery"] == "down" and answer["warnings"] == []


@aio
async def test_metrics_of_auth_challenges_conflicts_and_errors(
    cfg: Config, store: Store, discovery_store: Store
) -> None:
    record = status(
        auth={"mode": "enforce", "received": {"0a1b2c3d": 41, "deadbeef": 2}},
        errors={"recent": 2, "last": "x"},
        robot_id_conflict={"address": "10.7.0.8", "boot_id": 1, "last_seen": 1.0, "count": 6},
    )
    more = {"challenges": 17, "challenges_limited": 3, "invites": 2}
    record["counters"] = {**record["counters"], **more}
    discovery_store.write_status(record)
    async with serve(create_app(cfg, store)) as c:
        samples = parse_metrics(await (await c.get("/metrics")).text())
    modes = {m: samples[f'sdfr_auth_mode{{mode="{m}"}}'] for m in ("open", *auth.MODES)}
    assert modes == {"open": 0, "accept": 0, "sign": 0, "enforce": 1}
    assert samples['sdfr_auth_verified_total{key="0a1b2c3d"}'] == 41
    assert samples['sdfr_auth_verified_total{key="deadbeef"}'] == 2
    assert samples["sdfr_challenges_total"] == 17
    assert samples["sdfr_challenges_limited_total"] == 3
    assert samples["sdfr_invites_total"] == 2
    assert samples["sdfr_robot_id_conflicts_total"] == 6
    assert samples["sdfr_discovery_errors"] == 2


@aio
async def test_metrics_of_an_open_fleet_without_discovery(cfg: Config, store: Store) -> None:
    async with serve(create_app(cfg, store)) as c:
        samples = parse_metrics(await (await c.get("/metrics")).text())
    assert samples["sdfr_discovery_up"] == 0
    assert samples["sdfr_discovery_errors"] == 0
    assert samples["sdfr_challenges_total"] == 0
    assert samples["sdfr_robot_id_conflicts_total"] == 0
    assert not any(k.startswith("sdfr_auth_verified_total") for k in samples)
