"""GET /events with real daemons: the discovery layer's changes (a robot appears, changes its
services, leaves, falls silent) reach a watcher of another robot's API, and a lease that runs
out is withdrawn from the whole fleet."""

from __future__ import annotations

import threading
from collections.abc import Callable

import pytest

from netlab.lab import Lab
from sdfr.client import Client
from sdfr.client.calls import Change
from tests.support.waiting import poll

pytestmark = pytest.mark.root

BEACON = 0.5


def test_robot_changes_stream_to_a_watcher(fleet_factory: Callable[..., Lab]) -> None:
    lab = fleet_factory(3, beacon=BEACON, start=False)
    lab.start("r1", beacon_interval=BEACON)
    sock = lab.robot("r1").state_dir / "api.sock"
    seen: list[Change] = []
    with Client(unix_socket=sock) as c1:
        start = c1.events(since=None)["last_id"]

    done = threading.Event()

    def watch() -> None:
        try:
            with Client(unix_socket=sock) as w:
                for change in w.watch(["robot"], since=start, reconnect=False):
                    seen.append(change)
        except Exception:
            if not done.is_set():  # the stream ends with r1's daemon, once the test is done
                raise

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()

    def told(kind: str, robot: str) -> bool | str:
        return any(c.event == kind and c.robot_id == robot for c in seen) or str(
            [(c.event, c.robot_id) for c in seen]
        )

    lab.start("r2", beacon_interval=BEACON)
    lab.start("r3", beacon_interval=BEACON)
    poll("r2 appeared", lambda: told("robot.appeared", "r2"), 10)
    poll("r3 appeared", lambda: told("robot.appeared", "r3"), 10)
    lab.client("r2").publish("front cam", "camera/rgb", attributes={"fps": 30})
    poll("r2's services", lambda: told("robot.services", "r2"), 5)
    [services] = [c for c in seen if c.event == "robot.services" and c.robot_id == "r2"]
    assert [s["name"] for s in services.data["added"]] == ["front cam"]
    lab.stop("r2")  # a goodbye
    poll("r2 left", lambda: told("robot.left", "r2"), 5)
    lab.kill("r3")  # silence: unreachable after 3 beacons
    poll("r3 unreachable", lambda: told("robot.unreachable", "r3"), 3 * BEACON + 5)
    ids = [c.id for c in seen]
    assert ids == sorted(ids) and len(set(ids)) == len(ids)
    appeared = [c for c in seen if c.event == "robot.appeared" and c.robot_id == "r2"]
    assert appeared[0].data["new"] is True
    # The watcher ends with the stream, here and not in a later test.
    done.set()
    lab.stop("r1")
    watcher.join(timeout=15)
    assert not watcher.is_alive()


def test_a_lease_that_runs_out_leaves_the_fleet(fleet_factory: Callable[..., Lab]) -> None:
    lab = fleet_factory(2, beacon=BEACON)
    poll("r2 sees r1", lambda: "r1" in {n["robot_id"] for n in lab.client("r2").neighbors()}, 10)
    sid = lab.client("r1").publish("arm", "actuator/arm", ttl=1.0)

    def on_r2() -> set[str]:
        return {s["id"] for n in lab.client("r2").neighbors() for s in n["services"]}

    poll("r2 lists the arm", lambda: sid in on_r2() or str(on_r2()), 5)
    # Nobody renews it: r1 withdraws it, and r2 stops listing it, like an unpublish.
    poll("r2 no longer lists it", lambda: sid not in on_r2() or str(on_r2()), 1.0 + 5)
    kinds = [e.event for e in lab.client("r1").events(0)["events"]]
    assert "service.expired" in kinds
