"""The fleet's changes in a robot's log: the discovery layer's FleetLog fed by a real protocol
core (as `DiscoveryLayer._save` feeds it) on a simulated fleet, in virtual time."""

from __future__ import annotations

import logging
from typing import Any

from sdfr import wire
from sdfr.daemon.fleetlog import FleetLog, duration
from sdfr.daemon.logs import FIELDS
from sdfr.records.model import PeerRecord, Service, service_digest
from sdfr.testing.simnet import BEACON, SimNet


class _Lines(logging.Handler):
    """Every record of a private logger: its message and its structured fields."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.lines: list[tuple[str, dict[str, Any]]] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append((record.getMessage(), dict(getattr(record, FIELDS, {}))))


def _logger(name: str) -> tuple[logging.Logger, _Lines]:
    logger = logging.getLogger(f"tests.fleetlog.{name}")
    logger.propagate = False
    logger.setLevel(logging.INFO)
    lines = _Lines()
    logger.handlers = [lines]
    return logger, lines


def _svc(robot: str, name: str) -> Service:
    return Service(id=f"{robot}-{name}", name=name, type="t")


def _watch(net: SimNet, name: str, fleet_log: FleetLog) -> None:
    """After every event of the simulation, hand `name`'s changes to `fleet_log` as the
    discovery layer does when it saves them."""
    core = net.nodes[name].core

    def after() -> None:
        if core.has_dirty:
            fleet_log.observe(core.take_removed(), core.take_dirty(), net.now)

    net.after_event = after


def _events(lines: list[tuple[str, dict[str, Any]]], robot: str) -> list[str]:
    return [f["event"] for _, f in lines if f.get("robot") == robot]


def test_a_partition_and_merge_leaves_lines_that_explain_it() -> None:
    net = SimNet(seed=11)
    for r in ("r1", "r2", "r3"):
        net.add(
            r,
            services=[_svc(r, "camera"), _svc(r, "lidar")],
            beacon_interval=BEACON,
            ping_interval=BEACON / 2,
        )
    logger, said = _logger("partition")
    _watch(net, "r1", FleetLog(logger=logger))
    net.wait_until(lambda: net.all_see_all(), timeout=3.0)
    net.run_for(BEACON)
    texts = [t for t, _ in said.lines]
    first = [(t, f) for t, f in said.lines if f["event"] == "appeared"]
    assert {f["robot"] for _, f in first} == {"r2", "r3"}, texts
    assert all("(first seen)" in t and f["address"].startswith("10.1.0.") for t, f in first)
    # Their services are said once known: with the appearance, or in a line of their own.
    for robot in ("r2", "r3"):
        told = [f for _, f in said.lines if f.get("robot") == robot]
        names = {n for f in told for n in f.get("services", []) + f.get("added", [])}
        assert names == {"camera", "lidar"}, texts

    said.lines.clear()
    net.partition(["r1", "r2"], ["r3"])
    net.wait_until(lambda: not net.sees("r1", "r3"), timeout=10 * BEACON)
    net.run_for(BEACON)
    [(gone, fields)] = said.lines
    assert gone.startswith("robot r3 unreachable: silent for ") and "(was at 10.1.0.3)" in gone
    assert fields["event"] == "unreachable" and fields["silent_s"] > BEACON

    said.lines.clear()
    net.merge()
    net.wait_until(lambda: net.sees("r1", "r3"), timeout=10 * BEACON)
    net.run_for(BEACON)
    [(back, fields)] = said.lines
    assert back.startswith("robot r3 came back at 10.1.0.3 after "), back
    assert fields["event"] == "came_back" and fields["away_s"] > BEACON

    said.lines.clear()
    net.set_services("r2", 5, [_svc("r2", "camera"), _svc("r2", "map")])
    net.run_for(2 * BEACON)
    net.move("r2", "10.1.0.9")
    net.run_for(3 * BEACON)
    net.stop("r3")
    net.run_for(BEACON)
    texts = [t for t, _ in said.lines]
    assert "robot r2 services now version 5: added map; removed lidar" in texts, texts
    [services] = [f for _, f in said.lines if f["event"] == "services"]
    assert (services["added"], services["removed"], services["version"]) == (["map"], ["lidar"], 5)
    assert "robot r2 moved from 10.1.0.2 to 10.1.0.9" in texts, texts
    assert "robot r3 left (said byebye) from 10.1.0.3" in texts, texts
    # r2's address changed while r2 stayed listed: no other line about it.
    assert _events(said.lines, "r2") == ["services", "address"], said.lines


def test_a_robot_that_never_proves_itself_is_not_logged() -> None:
    """A forged robot id (beacons from an address that answers no ping) never reaches the
    records the core hands out: a flood of them writes nothing."""
    net = SimNet(seed=12)
    net.add("r1", beacon_interval=BEACON, ping_interval=BEACON / 2)
    logger, said = _logger("forged")
    _watch(net, "r1", FleetLog(logger=logger))
    for i in range(200):
        origin = wire.Origin(1, f"fake{i}", 1_700_000_000, 0, service_digest(()))
        beacon = wire.encode(wire.Alive(origin, f"http://10.1.7.{i % 250}:8701/d", 30))
        net.inject("r1", beacon, (f"10.1.7.{i % 250}", wire.DEFAULT_PORT))
        net.run_for(0.05)
    net.run_for(5 * BEACON)
    assert said.lines == []


def _rec(robot: str, reachable: bool = True, at: float = 0.0) -> PeerRecord:
    return PeerRecord(robot, "10.1.0.1", "", 1, 0, "", reachable, at, at, None, None, 0)


def test_a_flood_of_changes_is_bounded_and_counted() -> None:
    logger, said = _logger("flood")
    log = FleetLog(burst=3, rate=1.0, summary_every=10.0, logger=logger)
    log.observe([], [_rec(f"r{i}") for i in range(50)], now=0.0)
    assert len(said.lines) == 3  # the burst
    log.tick(1.0)
    assert said.lines[-1][0].startswith("47 more fleet changes not logged (47 appeared): ")
    assert said.lines[-1][1] == {"event": "suppressed", "suppressed": {"appeared": 47}}
    # A line a second after that (two tokens by t=2); the next count no sooner than
    # summary_every.
    log.observe([], [_rec(f"r{i}", reachable=False, at=1.0) for i in range(10)], now=2.0)
    assert [f["event"] for _, f in said.lines[4:]] == ["unreachable", "unreachable"]
    log.tick(5.0)
    assert len(said.lines) == 6
    log.tick(11.0)
    assert said.lines[-1][0].startswith("8 more fleet changes not logged (8 unreachable)")
    log.tick(30.0)
    assert len(said.lines) == 7  # nothing held: nothing said


def test_durations_read_as_a_person_says_them() -> None:
    assert [duration(s) for s in (0.84, 42.0, 750.0, 12600.0, 200000.0)] == [
        "0.8 s",
        "42 s",
        "12 min",
        "3.5 h",
        "2 d",
    ]
