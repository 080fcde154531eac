"""The durable state shared by the two layers."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from sdfr.records.model import PeerRecord, Service, service_digest
from sdfr.store import BOOT_EPOCH, Store, StoreError


def peer(robot: str, services: tuple[Service, ...], reachable: bool = True) -> PeerRecord:
    return PeerRecord(
        robot,
        "10.1.0.2",
        "http://10.1.0.2:8701/description.json",
        1,
        3,
        service_digest(services),
        reachable,
        100.0,
        200.0,
        0.9,
        1.5,
        10,
        services,
    )


def test_registrations_and_versions_survive_reopening(tmp_path: Path) -> None:
    a = Store(tmp_path)
    assert a.local_state() == (0, [])
    assert a.add_service(Service("s1", "cam", "sensor.camera")) == 1
    assert a.add_service(Service("s2", "lidar", "sensor.lidar")) == 2
    assert a.remove_service("s1") == 3
    assert a.remove_service("s1") is None
    with pytest.raises(StoreError, match="exists"):
        a.add_service(Service("s2", "dup", "x"))
    a.close()
    b = Store(tmp_path)
    assert b.local_state() == (3, [Service("s2", "lidar", "sensor.lidar")])


def test_boot_ids_only_grow(tmp_path: Path) -> None:
    now = 1_800_000_000.0
    first = now - BOOT_EPOCH
    # Three starts in one second still get three ids.
    assert [Store(tmp_path).next_boot_id(now) for _ in range(3)] == [first, first + 1, first + 2]
    # A clock that went back does not bring an old id back.
    assert Store(tmp_path).next_boot_id(now - 1000) == first + 3


def test_boot_ids_are_new_even_when_the_state_dir_is_lost(tmp_path: Path) -> None:
    before = Store(tmp_path / "a").next_boot_id(1_800_000_000.0)
    after = Store(tmp_path / "wiped").next_boot_id(1_800_000_060.0)
    assert after > before
    # A clock past what BOOTID can hold starts over rather than overflow.
    assert Store(tmp_path / "far").next_boot_id(BOOT_EPOCH + 2.0**31) == 1


def test_forgotten_peers_are_deleted(tmp_path: Path) -> None:
    store = Store(tmp_path)
    store.save_peers([peer("r1", ()), peer("r2", ())])
    store.delete_peers(["r1", "r9"])
    assert [p.robot_id for p in store.load_peers()] == ["r2"]


def test_history_round_trip_and_cross_connection_visibility(tmp_path: Path) -> None:
    writer, reader = Store(tmp_path), Store(tmp_path)
    before = reader.data_version()
    svcs = (Service("x", "arm", "actuator.arm", "http://a/", {"dof": 6, "ok": True}),)
    writer.save_peers([peer("r2", svcs), peer("r3", (), reachable=False)])
    assert reader.data_version() != before
    got = {p.robot_id: p for p in reader.load_peers()}
    assert got["r2"] == peer("r2", svcs) and not got["r3"].reachable
    writer.mark_all_unreachable()
    assert not any(p.reachable for p in reader.load_peers())


def test_status_is_a_file_that_does_not_touch_the_database(tmp_path: Path) -> None:
    writer, reader = Store(tmp_path), Store(tmp_path)
    assert reader.read_status() == {}
    version = reader.data_version()
    writer.write_status({"pid": 1})
    status = reader.read_status()
    assert status["pid"] == 1 and status["heartbeat"] > 0
    assert reader.data_version() == version


def test_unusable_state_dir_is_a_clear_error(tmp_path: Path) -> None:
    (tmp_path / "state.db").write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(StoreError, match="not a usable SDfR database"):
        Store(tmp_path)
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(StoreError, match="cannot create"):
        Store(blocker / "sub")


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"name": "x", "type": "t", "attributes": {"a": float("inf")}}, "attributes.a"),
        ({"name": "x", "type": "t\n"}, "type"),
        ({"name": "", "type": "t"}, "name"),
    ],
)
def test_service_validation_names_the_field(body: dict[str, object], field: str) -> None:
    from sdfr.errors import ValidationError

    with pytest.raises(ValidationError) as info:
        Service.from_json(body, service_id="abc")
    assert info.value.field == field


def test_ids_with_a_trailing_newline_are_refused() -> None:
    from sdfr.errors import ValidationError
    from sdfr.records.model import check_robot_id

    with pytest.raises(ValidationError):
        check_robot_id("abc\n")
    with pytest.raises(ValidationError):
        Service.from_json({"id": "a\n", "name": "x", "type": "t"})


def test_a_peer_saved_again_under_one_version_shows_its_new_services(tmp_path: Path) -> None:
    """A peer is stored before its set is fetched, then with it: same boot and version."""
    writer, reader = Store(tmp_path), Store(tmp_path)
    svcs = (Service("m", "map", "slam.map"),)
    empty = PeerRecord(
        "r1",
        "10.1.0.1",
        "http://10.1.0.1:8701/",
        1,
        1,
        service_digest(svcs),
        True,
        1.0,
        1.0,
        None,
        None,
        0,
        (),
    )
    writer.save_peers([empty])
    assert reader.load_peers()[0].services == ()
    writer.save_peers([dataclasses.replace(empty, services=svcs)])
    assert reader.load_peers()[0].services == svcs


def test_reloading_the_local_set_parses_only_what_changed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Both layers reload the local set after every change: at the paper's 70 services each
    reload parsed all 70 (most of a publish's time in the API). Now only new ones are parsed,
    and the set read is the same as a fresh store's."""
    from sdfr.store import db

    store = Store(tmp_path)
    for i in range(70):
        store.add_service(Service(id=f"s{i:02d}", name=f"cam{i}", type="sensor.camera"))
    store.local_state()
    parsed: list[str] = []
    real = db._service_from_row
    monkeypatch.setattr(db, "_service_from_row", lambda body: parsed.append(body) or real(body))
    store.add_service(Service(id="new", name="lidar", type="sensor.lidar"))
    store.remove_service("s03")
    version, services = store.local_state()
    assert len(parsed) == 1 and '"new"' in parsed[0]
    monkeypatch.undo()
    assert (version, services) == Store(tmp_path).local_state()
    assert [s.id for s in services][-1] == "new" and "s03" not in {s.id for s in services}
