"""The discovery layer's status record: what one layer writes, the other reads, typed."""

from __future__ import annotations

import json

from sdfr.records.status import FORMAT, Auth, Conflict, DiscoveryStatus, Errors, StateDir


def test_a_status_survives_json_whole() -> None:
    status = DiscoveryStatus(
        pid=42,
        heartbeat=1_800_000_000.5,
        robot_id="r1",
        address="10.1.0.1",
        boot_id=219_000_000,
        auth=Auth(mode="sign", primary="ab12cd34", keys=("ab12cd34",), received={"ab12cd34": 7}),
        robot_id_conflict=Conflict("10.1.0.9", 3, 1_800_000_000.0, 2),
        errors=Errors(recent=3, last="timer failed"),
        state=StateDir(writable=False, reason="full", error="the state directory is full"),
    )
    assert DiscoveryStatus.from_json(json.loads(json.dumps(status.to_json()))) == status


def test_what_is_not_a_status_reads_as_none() -> None:
    good = DiscoveryStatus(pid=1, heartbeat=2.0).to_json()
    assert DiscoveryStatus.from_json(good) is not None
    for bad in (
        None,
        [],
        {},  # no pid, no heartbeat
        {**good, "pid": "1"},
        {**good, "heartbeat": True},
        {**good, "auth": {"mode": 3}},
        {**good, "counters": {"rejects": {"x": "many"}}},
        {**good, "format": FORMAT + 1},  # a newer layer's record: not guessed at
    ):
        assert DiscoveryStatus.from_json(bad) is None, bad


def test_an_older_writer_or_a_newer_one_with_more_fields_still_reads() -> None:
    minimal = {"pid": 5, "heartbeat": 3}  # fields added since default
    assert DiscoveryStatus.from_json(minimal) == DiscoveryStatus(pid=5, heartbeat=3.0)
    more = {**minimal, "something_new": {"x": 1}}
    assert DiscoveryStatus.from_json(more) == DiscoveryStatus(pid=5, heartbeat=3.0)
