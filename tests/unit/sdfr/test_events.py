"""The changes feed's logic (sdfr.records.events.Tracker) and its log in the store."""

from __future__ import annotations

import dataclasses
import json
import sqlite3
from pathlib import Path

import pytest

from sdfr.records import events
from sdfr.records.events import Tracker
from sdfr.records.model import PeerRecord, Service
from sdfr.store import EVENT_LOG_MAX, Add, Expire, Remove, Renew, Store

CAM = Service("c1", "cam", "camera/rgb", None, {"fps": 30})
LIDAR = Service("l1", "lidar", "lidar")


def rec(rid: str = "r2", **kw: object) -> PeerRecord:
    base = PeerRecord(
        robot_id=rid, address="10.3.0.2", location="http://10.3.0.2:8701/", boot_id=1,
        version=1, digest="d" * 16, reachable=True, first_seen=1.0, last_seen=2.0,
        indicator=None, rtt_ms=None, pings=0, services=(CAM,),
    )  # fmt: skip
    return dataclasses.replace(base, **kw)  # type: ignore[arg-type]


def kinds(evs: list[events.Event]) -> list[str]:
    return [e.kind for e in evs]


def test_appeared_services_address_left_unreachable() -> None:
    t = Tracker((0.5, 0.8))
    [appeared] = t.observe(rec())
    assert appeared.kind == "robot.appeared" and appeared.data["new"] is True
    assert appeared.data["services"] == [CAM.to_json()]
    assert t.observe(rec()) == []  # nothing changed: nothing told
    [changed] = t.observe(rec(services=(dataclasses.replace(CAM, name="cam2"), LIDAR)))
    assert changed.kind == "robot.services"
    assert changed.data["added"] == [LIDAR.to_json()] and changed.data["removed"] == []
    assert [s["name"] for s in changed.data["changed"]] == ["cam2"]  # type: ignore[attr-defined]
    assert kinds(t.observe(rec(services=(LIDAR,), address="10.3.0.9"))) == [
        "robot.services",
        "robot.address",
    ]
    assert kinds(t.observe(rec(services=(LIDAR,), address="10.3.0.9", reachable=False))) == [
        "robot.unreachable"
    ]
    [again] = t.observe(rec(services=(LIDAR,), address="10.3.0.9"))
    assert again.kind == "robot.appeared" and again.data["new"] is False
    [left] = t.observe(rec(services=(LIDAR,), address="10.3.0.9", reachable=False, departed=True))
    assert left.kind == "robot.left"
    assert t.forget("r2").kind == "robot.forgotten"


def test_indicator_crossings_with_hysteresis() -> None:
    t = Tracker((0.5, 0.8))
    t.observe(rec())
    assert t.observe(rec(indicator=1.0)) == []  # the first settled ping sets the band
    [down] = t.observe(rec(indicator=0.75))
    assert down.data == {"indicator": 0.75, "threshold": 0.8, "direction": "down"}
    assert t.observe(rec(indicator=0.8)) == []  # back at the threshold: not clear of it yet
    assert t.observe(rec(indicator=0.75)) == []
    [down2] = t.observe(rec(indicator=0.3))
    assert down2.data["threshold"] == 0.5 and down2.data["direction"] == "down"
    assert t.observe(rec(indicator=0.55)) == []  # within the hysteresis above 0.5
    [up] = t.observe(rec(indicator=0.65))
    assert up.data["threshold"] == 0.5 and up.data["direction"] == "up"
    [up2] = t.observe(rec(indicator=1.0))
    assert up2.data["threshold"] == 0.8
    # Unreachable ends the band: no indicator events while gone, a fresh band after.
    t.observe(rec(indicator=0.0, reachable=False))
    t.observe(rec(indicator=0.2))
    assert t.observe(rec(indicator=0.3)) == []


def test_rollback_tells_again_what_was_not_saved() -> None:
    t = Tracker()
    undo = t.checkpoint()
    assert kinds(t.observe(rec())) == ["robot.appeared"]
    t.rollback(undo)
    assert kinds(t.observe(rec())) == ["robot.appeared"]


def test_a_large_service_set_is_left_out_of_the_event() -> None:
    many = tuple(Service(f"s{i}", "x" * 100, "t") for i in range(100))
    [appeared] = Tracker().observe(rec(services=many))
    assert appeared.data["services_truncated"] is True and appeared.data["services_count"] == 100
    assert len(appeared.body(1, 0.0)) < 2000


def test_kind_filter() -> None:
    assert events.kind_filter(["robot"]) == {k for k in events.KINDS if k.startswith("robot.")}
    assert events.kind_filter(["service.expired"]) == {"service.expired"}
    with pytest.raises(ValueError, match="'robots' is no event kind"):
        events.kind_filter(["robots"])


# -- the log in the store -------------------------------------------------------------------------


def bodies(store: Store, after: int = 0) -> list[dict[str, object]]:
    return [json.loads(e.body) for e in store.events_after(after, 10_000)]


def test_registrations_make_events_in_their_transaction(tmp_path: Path) -> None:
    s = Store(tmp_path)
    assert s.apply([Add(CAM, 30.0)], now=1000.0) == [1]
    assert s.lease("c1") is not None and s.lease("c1").expires == 1030.0  # type: ignore[union-attr]
    assert s.apply([Renew("c1")], now=1010.0) == [0]
    assert s.lease("c1").expires == 1040.0  # type: ignore[union-attr]
    # An expiry of an end that was renewed since does nothing.
    assert s.apply([Expire("c1", 1030.0)], now=1035.0) == [None]
    assert s.expire_overdue(1041.0) == ["c1"]
    assert s.apply([Add(LIDAR), Remove("l1"), Remove("l1")]) == [3, 4, None]
    got = bodies(s)
    assert [b["event"] for b in got] == [
        "service.published",
        "service.expired",
        "service.published",
        "service.unpublished",
    ]
    assert got[0]["ttl"] == 30.0 and got[1]["service_id"] == "c1"
    ids = [int(b["id"]) for b in got]  # type: ignore[call-overload]
    assert ids == sorted(set(ids))
    s.close()


def test_event_ids_grow_past_lost_ones_and_the_log_is_bounded(tmp_path: Path) -> None:
    s = Store(tmp_path)
    s.save_peers([rec()], [events.Event("robot.appeared", "r2")], now=2000.0)
    first = s.last_event_id()
    assert first == 2000 * 1_000_000
    # A power cut lost that event (never fsynced): the next id still grows, with the clock.
    s._db.execute("DELETE FROM events")
    s.save_peers([rec()], [events.Event("robot.unreachable", "r2")], now=2000.5)
    assert s.last_event_id() > first
    many = [events.Event("robot.indicator", "r2")] * (EVENT_LOG_MAX + 10)
    s.save_peers([], many, now=2001.0)
    count = s._db.execute("SELECT COUNT(*) FROM events").fetchone()[0]
    assert count == EVENT_LOG_MAX
    assert s.events_pruned() == min(e.id for e in s.events_after(0, 1)) - 1
    s.close()


def test_a_schema_1_state_directory_is_migrated(tmp_path: Path) -> None:
    db = sqlite3.connect(tmp_path / "state.db")
    db.executescript(
        "CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);"
        "INSERT INTO meta VALUES ('schema', '1'), ('local_version', '1');"
        "CREATE TABLE local_services (id TEXT PRIMARY KEY, seq INTEGER NOT NULL, "
        "body TEXT NOT NULL);"
    )
    db.execute("INSERT INTO local_services VALUES ('c1', 1, ?)", (json.dumps(CAM.to_json()),))
    db.commit()
    db.close()
    s = Store(tmp_path)
    assert s.local_state() == (1, [CAM])  # nothing lost
    assert s.lease("c1") is None
    assert s.get_meta("schema") == "3"
    s.close()
