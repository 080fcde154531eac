"""The ROS bridge's core without ROS: changes from neighbour lists, parameters, requests,
health, and a real sdfrd that the bridge starts (and stops) or finds running."""

from __future__ import annotations

import http.server
import os
import shlex
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from xml.etree import ElementTree

import pytest
import yaml

from sdfr.client import Client
from sdfr.errors import ApiError, ConfigError
from sdfr.records.model import Service
from sdfr.ros.core import (
    QUALITY_REFRESH,
    Bridge,
    BridgeError,
    Change,
    ChangeKind,
    Diagnosis,
    Level,
    Robot,
    ServiceRequest,
    Snapshot,
    diagnosis_of,
    diff,
    robots_from_json,
    services_from_json,
)
from sdfr.ros.params import DESCRIPTIONS, NodeParams
from sdfr.ros.source import EventStreamSource, PollingSource
from sdfr.ros.spawn import SpawnError
from tests.support.api import free_port

REPO = Path(__file__).resolve().parents[3]
K = ChangeKind


def svc(sid: str, name: str = "cam", **attrs: str | int | float | bool) -> Service:
    return Service(id=sid, name=name, type="sensor.camera", attributes=attrs)


def robot(rid: str, *services: Service, address: str = "10.1.0.1", indicator: float = 1.0) -> Robot:
    return Robot(rid, address, True, indicator, 2.0, 100.0, services)


def snap(t: float, *robots: Robot) -> Snapshot:
    return Snapshot(t, robots)


def kinds(changes: Sequence[Change]) -> list[tuple[ChangeKind, str, str | None]]:
    return [(c.kind, c.robot_id, c.service.id if c.service else None) for c in changes]


# -- changes ---------------------------------------------------------------------------------


def test_an_arriving_robot_then_its_services_and_the_reverse_when_it_leaves() -> None:
    a = robot("a", svc("s2"), svc("s1"))
    arrived = diff(None, snap(1.0, a))
    assert kinds(arrived) == [(K.ROBOT_ADDED, "a", None), (K.SERVICE_ADDED, "a", "s1"),
                              (K.SERVICE_ADDED, "a", "s2")]  # fmt: skip
    assert all(c.stamp == 1.0 and c.address == "10.1.0.1" for c in arrived)
    left = diff(snap(1.0, a), snap(2.0))
    assert kinds(left) == [(K.SERVICE_REMOVED, "a", "s1"), (K.SERVICE_REMOVED, "a", "s2"),
                           (K.ROBOT_REMOVED, "a", None)]  # fmt: skip


def test_service_changes_of_a_robot_that_stays() -> None:
    before = snap(1.0, robot("a", svc("s1", fps=30), svc("s2")), robot("b", svc("t")))
    after = snap(2.0, robot("a", svc("s1", fps=15), svc("s3")), robot("b", svc("t")))
    assert kinds(diff(before, after)) == [
        (K.SERVICE_UPDATED, "a", "s1"),
        (K.SERVICE_REMOVED, "a", "s2"),
        (K.SERVICE_ADDED, "a", "s3"),
    ]
    updated = diff(before, after)[0].service
    assert updated is not None and updated.attributes == {"fps": 15}


def test_an_address_change_is_a_robot_update_and_link_quality_is_no_change() -> None:
    before = snap(1.0, robot("a", svc("s1"), indicator=1.0))
    assert kinds(diff(before, snap(2.0, robot("a", svc("s1"), address="10.1.0.9")))) == [
        (K.ROBOT_UPDATED, "a", None)
    ]
    assert diff(before, snap(2.0, robot("a", svc("s1"), indicator=0.4))) == []


class Recorder:
    """A Sink that keeps what the bridge gives it."""

    def __init__(self) -> None:
        self.lists: list[tuple[Snapshot, str]] = []
        self.events: list[Change] = []
        self.diagnoses: list[Diagnosis] = []
        self.lock = threading.Lock()

    def neighbors(self, snapshot: Snapshot, robot_id: str) -> None:
        with self.lock:
            self.lists.append((snapshot, robot_id))

    def changes(self, changes: Sequence[Change]) -> None:
        with self.lock:
            self.events += changes

    def diagnostics(self, diagnosis: Diagnosis) -> None:
        with self.lock:
            self.diagnoses.append(diagnosis)


def test_neighbors_go_out_on_a_change_and_quality_alone_at_most_every_refresh() -> None:
    sink = Recorder()
    bridge = Bridge(NodeParams(spawn=False), sink)
    try:
        bridge.on_snapshot(snap(0.0))  # the first list goes out, empty or not
        bridge.on_snapshot(snap(1.0))
        assert len(sink.lists) == 1 and sink.events == []
        bridge.on_snapshot(snap(2.0, robot("a", svc("s1"))))
        assert len(sink.lists) == 2 and [c.kind for c in sink.events] == [
            K.ROBOT_ADDED,
            K.SERVICE_ADDED,
        ]
        bridge.on_snapshot(snap(3.0, robot("a", svc("s1"), indicator=0.5)))
        assert len(sink.lists) == 2  # only the indicator moved, 1 s after the last list
        bridge.on_snapshot(snap(2.0 + QUALITY_REFRESH, robot("a", svc("s1"), indicator=0.5)))
        assert len(sink.lists) == 3 and sink.lists[-1][0].robots[0].indicator == 0.5
        assert len(sink.events) == 2
    finally:
        bridge.close()


# -- parameters ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("values", "named"),
    [
        ({"api": "localhost"}, "parameter api: expected HOST:PORT"),
        ({"poll_interval": 0.0}, "parameter poll_interval: must be 0.02-10.0 seconds, got 0.0"),
        ({"poll_interval": 60}, "parameter poll_interval"),
        ({"diagnostics_period": 0.01}, "parameter diagnostics_period"),
        ({"fleet": 256}, "parameter fleet: must be 0-255"),
        ({"fleet": "3"}, "parameter fleet: expected int, got '3'"),
        ({"spawn": "yes"}, "parameter spawn: expected bool"),
        ({"sdfrd_command": "  "}, "parameter sdfrd_command: must name a program"),
        ({"sdfrd_args": "--iface 'wlan0"}, "parameter sdfrd_args: No closing quotation"),
        ({"pol_interval": 1.0}, "unknown parameter(s) pol_interval (known: api, spawn"),
    ],
)
def test_a_bad_parameter_is_refused_naming_it(values: dict[str, object], named: str) -> None:
    with pytest.raises(ConfigError) as err:
        NodeParams.from_mapping(values)
    assert named in str(err.value)


def test_parameters_from_ros_and_the_command_that_starts_sdfrd() -> None:
    params = NodeParams.from_mapping(
        {"api": "127.0.0.1:9000", "fleet": 3, "poll_interval": 1, "sdfrd_config": "/etc/r.toml",
         "sdfrd_args": "--iface wlan0 --robot-id 'r 1'", "sdfrd_command": "/opt/sdfr/bin/sdfrd"}
    )  # fmt: skip
    assert params.poll_interval == 1.0 and isinstance(params.poll_interval, float)
    assert params.sdfrd_argv() == [
        "/opt/sdfr/bin/sdfrd", "--api", "127.0.0.1:9000", "--config", "/etc/r.toml",
        "--fleet", "3", "--iface", "wlan0", "--robot-id", "r 1",
    ]  # fmt: skip
    assert NodeParams().sdfrd_argv() == ["sdfrd", "--api", "127.0.0.1:8700"]


def test_the_ros2_params_file_and_the_ros1_launch_file_list_every_parameter_with_its_default() -> (
    None
):
    defaults = NodeParams()
    names = list(DESCRIPTIONS)
    yaml_file = REPO / "ros" / "sdfr_ros" / "config" / "sdfr.params.yaml"
    listed = yaml.safe_load(yaml_file.read_text())["sdfr"]["ros__parameters"]
    assert list(listed) == names
    assert NodeParams.from_mapping(listed) == defaults
    launch = ElementTree.parse(REPO / "ros" / "sdfr_ros" / "launch" / "sdfr.launch").getroot()
    args = {a.get("name"): a.get("default") for a in launch.iter("arg")}
    assert list(args) == names
    for name, default in args.items():
        assert default is not None
        assert str(getattr(defaults, name)).lower() == default.lower(), name
    node = launch.find("node")
    assert node is not None and node.get("name") == "sdfr"
    assert [p.get("name") for p in node.iter("param")] == names


# -- requests and the daemon's answers -------------------------------------------------------


def test_a_service_without_an_id_gets_one_from_its_type_and_name() -> None:
    a = ServiceRequest(name="front", type="sensor.camera")
    assert (
        a.service_id() == ServiceRequest(name="front", type="sensor.camera", url="x").service_id()
    )
    assert a.service_id() != ServiceRequest(name="rear", type="sensor.camera").service_id()
    assert a.service_id().startswith("ros-") and len(a.service_id()) == 16
    assert ServiceRequest(name="front", type="t", id="mine").service_id() == "mine"


def test_a_malformed_answer_of_the_daemon_names_what_was_wrong() -> None:
    good = {"robot_id": "a", "address": "10.1.0.1", "reachable": True, "indicator": None,
            "rtt_ms": None, "last_seen": 5.0, "services": [], "extra": 1}  # fmt: skip
    assert robots_from_json([good])[0].robot_id == "a"
    with pytest.raises(BridgeError, match=r"for neighbors: .*reachable"):
        robots_from_json([{**good, "reachable": "yes"}])


def test_a_field_a_newer_daemon_adds_to_services_does_not_break_the_bridge() -> None:
    service = {"id": "s1", "name": "map", "type": "nav.map", "url": None, "attributes": {},
               "added_later": {"x": 1}}  # fmt: skip
    robot = {"robot_id": "a", "address": "10.1.0.1", "reachable": True, "indicator": None,
             "rtt_ms": None, "last_seen": 5.0, "services": [service]}  # fmt: skip
    [seen] = robots_from_json([robot])[0].services
    assert (seen.id, seen.name, seen.type) == ("s1", "map", "nav.map")
    [mine] = services_from_json([{**service, "ttl": None, "expires": None}])
    assert mine.id == "s1"
    with pytest.raises(BridgeError, match="for neighbors"):  # what it reads is still checked
        robots_from_json([{**robot, "services": [{**service, "name": 7}]}])


def test_health_as_a_diagnosis() -> None:
    ok = diagnosis_of(
        {"status": "ok", "discovery": "up", "state": "ok", "warnings": []}, "r1", None
    )
    assert (ok.level, ok.message, ok.robot_id) == (Level.OK, "sdfrd is up", "r1")
    assert ("started_by_node", "no") in ok.values
    warn = diagnosis_of({"status": "warning", "warnings": ["two daemons claim r1"]}, "r1", None)
    assert (warn.level, warn.message) == (Level.WARN, "two daemons claim r1")
    down = diagnosis_of(
        {"status": "degraded", "discovery": "down", "state": "ok", "discovery_error": None},
        "",
        None,
    )
    assert down.level is Level.ERROR and "discovery down" in down.message


# -- with a real sdfrd -----------------------------------------------------------------------


def sdfrd_params(tmp: Path, **kw: object) -> NodeParams:
    """A node's parameters for an sdfrd of its own on the loopback (ports free now, a fleet
    and a robot id of this test alone: other daemons may be on this machine's loopback)."""
    port = free_port()
    args = [
        "--iface", "lo", "--describe", f"127.0.0.1:{free_port()}",
        "--state-dir", str(tmp / "state"),
        "--robot-id", f"ros-core-{os.getpid()}-{port}", "--beacon-interval", "0.5",
    ]  # fmt: skip
    values: dict[str, object] = {
        "api": f"127.0.0.1:{port}",
        "sdfrd_command": shlex.join([sys.executable, "-m", "sdfr.daemon.supervisor"]),
        "sdfrd_args": shlex.join(args),
        "fleet": 200 + port % 50,
        "sdfrd_log": str(tmp / "sdfrd.log"),
        "diagnostics_period": 0.2,
        "poll_interval": 0.05,
    }
    values.update(kw)
    return NodeParams.from_mapping(values)


def answers(api: str) -> bool:
    with Client(api, timeout=1.0, retry_delays=()) as client:
        try:
            client.health()
        except ApiError as exc:
            return exc.status != 0
    return True


def wait_for(what: str, cond: object, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():  # type: ignore[operator]
        if time.monotonic() > deadline:
            pytest.fail(f"not within {timeout} s: {what}")
        time.sleep(0.05)


@pytest.fixture
def spawned(tmp_path: Path) -> Iterator[tuple[Bridge, Recorder]]:
    """A bridge that started its own sdfrd (closed, and so the daemon stopped, after)."""
    sink = Recorder()
    bridge = Bridge(sdfrd_params(tmp_path), sink)
    try:
        bridge.start()
        yield bridge, sink
    finally:
        bridge.close()


def test_the_bridge_starts_sdfrd_when_none_answers_and_stops_it_on_close(tmp_path: Path) -> None:
    sink = Recorder()
    params = sdfrd_params(tmp_path)
    assert not answers(params.api)
    bridge = Bridge(params, sink)
    try:
        bridge.start()
        assert bridge.spawned is not None and answers(params.api)
        proc = bridge.spawned.proc
        assert bridge.robot_id.startswith("ros-core-")
        wait_for("a first neighbour list and a diagnosis", lambda: sink.lists and sink.diagnoses)
        first = sink.diagnoses[0]
        assert first.level in (Level.OK, Level.WARN), first
        assert ("started_by_node", "yes") in first.values and first.robot_id == bridge.robot_id
        assert sink.lists[0][1] == bridge.robot_id
    finally:
        bridge.close()
    assert proc.returncode is not None and not answers(params.api)


def test_a_daemon_that_answers_already_is_used_and_left_running(
    spawned: tuple[Bridge, Recorder], tmp_path: Path
) -> None:
    owner, _ = spawned
    sink = Recorder()
    guest = Bridge(owner.params, sink)
    guest.start()
    try:
        assert guest.spawned is None and guest.robot_id == owner.robot_id
        wait_for("a diagnosis", lambda: sink.diagnoses)
        assert ("started_by_node", "no") in sink.diagnoses[0].values
    finally:
        guest.close()
    assert answers(owner.params.api)  # the guest did not stop the owner's daemon


def test_publish_list_search_and_unpublish_through_the_daemon(
    spawned: tuple[Bridge, Recorder],
) -> None:
    bridge, _ = spawned
    request = ServiceRequest(name="front", type="sensor.camera", attributes={"fps": 30, "hd": True})
    sid = bridge.publish(request)
    assert sid == request.service_id()
    assert bridge.publish(request) == sid  # the same message again: stored once
    listing = bridge.listing()
    assert [s.id for s in listing.services] == [sid] and listing.robot_id == bridge.robot_id
    assert listing.services[0].attributes == {"fps": 30, "hd": True}
    # The newest message under one id wins.
    bridge.publish(ServiceRequest(name="front", type="sensor.camera", attributes={"fps": 15}))
    assert bridge.listing().services[0].attributes == {"fps": 15}
    # A robot's own services are not its neighbours'; nobody else offers this one here.
    assert bridge.search("sensor.camera", {"fps": 15}) == ()
    with pytest.raises(BridgeError, match="give a type or at least one attribute"):
        bridge.search("", {})
    with pytest.raises(BridgeError, match=r"cannot publish 'bad': .*type"):
        bridge.publish(ServiceRequest(name="bad", type="no spaces allowed"))
    assert bridge.unpublish(request) == sid
    assert bridge.listing().services == ()
    with pytest.raises(BridgeError, match="this robot has no such service"):
        bridge.unpublish(request)


def test_without_a_daemon_and_without_spawning_requests_fail_and_health_says_why(
    tmp_path: Path,
) -> None:
    sink = Recorder()
    params = sdfrd_params(tmp_path, spawn=False)
    bridge = Bridge(params, sink)
    bridge.start()
    try:
        assert bridge.spawned is None
        wait_for("a diagnosis", lambda: sink.diagnoses)
        d = sink.diagnoses[0]
        assert d.level is Level.ERROR and f"cannot reach sdfrd at {params.api}" in d.message
        with pytest.raises(BridgeError, match="is sdfrd running"):
            bridge.publish(ServiceRequest(name="x", type="t"))
        assert sink.lists == []
    finally:
        bridge.close()


def test_a_daemon_that_cannot_start_is_an_error_saying_why(tmp_path: Path) -> None:
    failing = sdfrd_params(tmp_path, sdfrd_args="--fleet 999")
    with pytest.raises(SpawnError, match=r"exited with status 2 before it answered") as err:
        Bridge(failing, Recorder()).start()
    assert "fleet" in str(err.value)  # sdfrd's own complaint, from its output
    missing = sdfrd_params(tmp_path, sdfrd_command="no-such-sdfrd")
    with pytest.raises(SpawnError, match="parameter sdfrd_command: 'no-such-sdfrd' is not on PATH"):
        Bridge(missing, Recorder()).start()


def test_the_polling_source_reads_the_list_until_stopped(spawned: tuple[Bridge, Recorder]) -> None:
    bridge, _ = spawned
    source = PollingSource(lambda: Client(bridge.params.api, timeout=2.0), 0.05)
    got: list[Snapshot] = []
    stop = threading.Event()
    thread = threading.Thread(target=source.run, args=(got.append, stop))
    thread.start()
    try:
        wait_for("three lists", lambda: len(got) >= 3)
    finally:
        stop.set()
        thread.join(timeout=10)
    assert not thread.is_alive() and source.last_error == ""
    assert got[0].stamp <= got[-1].stamp


def test_fields_a_newer_sdfrd_adds_are_ignored_and_bad_ones_named() -> None:
    leased = {
        "id": "cam", "name": "camera", "type": "sensor.camera", "url": None,
        "attributes": {"fps": 30}, "ttl": 10.0, "expires": 1.7e9,
    }  # fmt: skip
    (service,) = services_from_json([leased])
    assert (service.id, service.attributes) == ("cam", {"fps": 30})
    with pytest.raises(BridgeError, match=r"for services: .*name"):
        services_from_json([{**leased, "name": 5}])


def test_the_bridge_follows_the_change_stream_and_stops_at_once(
    spawned: tuple[Bridge, Recorder],
) -> None:
    bridge, sink = spawned
    source = bridge.source
    assert isinstance(source, EventStreamSource)
    wait_for("the stream followed", lambda: source.streaming and sink.lists, timeout=10)
    t0 = time.monotonic()
    bridge.close()  # stopping does not wait out the source's refresh period
    assert time.monotonic() - t0 < 3.0


class _OlderSdfrd(http.server.BaseHTTPRequestHandler):
    """An sdfrd from before the change stream: GET /events is not found."""

    def do_GET(self) -> None:
        body = b'{"neighbors": []}' if self.path == "/neighbors" else b'{"error": "not found"}'
        self.send_response(200 if self.path == "/neighbors" else 404)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args: object) -> None:
        pass


def test_a_daemon_without_the_change_stream_is_polled() -> None:
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _OlderSdfrd)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    api = f"127.0.0.1:{server.server_address[1]}"
    delivered: list[object] = []
    stop = threading.Event()

    def connect() -> Client:
        return Client(api, timeout=2.0, retry_delays=())

    source = EventStreamSource(connect, PollingSource(connect, 0.05), refresh=60.0)
    runner = threading.Thread(target=source.run, args=(delivered.append, stop))
    runner.start()
    try:
        wait_for("lists read by polling", lambda: len(delivered) >= 5, timeout=10)
        assert not source.streaming
    finally:
        stop.set()
        runner.join(5)
        server.shutdown()
        server.server_close()
    assert not runner.is_alive()
