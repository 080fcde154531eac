"""The paper bench's pure parts: bytes from pcaps, how long changes took to be seen, what the
side-by-side makes of its watchers' notes, and the load's unpublish scheduler."""

from __future__ import annotations

import random
import struct
import threading
from pathlib import Path
from typing import Any

import pytest

from bench.paper_load import Board
from bench.paper_measure import Reading, mdns_messages, propagation, udp_traffic, usage
from bench.side_by_side import (
    everyone_lists,
    first_time,
    halves_apart,
    nobody_lists,
    nobody_lists_these,
    own_services,
    replay,
)
from bench.zc_node import TYPE, instance, owner

MINE = "02:00:00:00:00:01"
OTHER = "02:00:00:00:00:02"


def frame(src_mac: str, sport: int, dport: int, payload: bytes) -> bytes:
    eth = bytes.fromhex(("01005e7ffffa" + src_mac.replace(":", "")) + "0800")
    udp = struct.pack("!HHHH", sport, dport, 8 + len(payload), 0) + payload
    ip = struct.pack(
        "!BBHHHBBH4s4s", 0x45, 0, 20 + len(udp), 0, 0, 1, 17, 0, b"\n\x01\x00\x01",
        b"\xef\xff\xff\xfa",
    )  # fmt: skip
    return eth + ip + udp


def pcap(path: Path, frames: list[tuple[float, bytes]]) -> Path:
    out = struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, 1)
    for t, f in frames:
        sec = int(t)
        out += struct.pack("<IIII", sec, int((t - sec) * 1e6), len(f), len(f)) + f
    path.write_bytes(out)
    return path


def test_udp_traffic_counts_what_a_robot_sent_and_received_per_port(tmp_path: Path) -> None:
    p = pcap(
        tmp_path / "r1.pcap",
        [
            (10.0, frame(MINE, 1900, 1900, b"x" * 100)),
            (11.0, frame(OTHER, 1900, 1900, b"y" * 50)),
            (11.5, frame(OTHER, 5353, 5353, b"z" * 70)),
            (12.0, frame(MINE, 40000, 1900, b"w" * 10)),  # to port 1900: counted
            (30.0, frame(MINE, 1900, 1900, b"late" * 10)),  # outside the window
        ],
    )
    got = udp_traffic(p, MINE, [1900, 5353], (9.0, 20.0))
    tx, rx = got[1900].tx, got[1900].rx
    assert (tx.datagrams, tx.payload_bytes, tx.frame_bytes) == (2, 110, 194)
    assert (rx.datagrams, rx.payload_bytes) == (1, 50)
    tx, rx = got[5353].tx, got[5353].rx
    assert (tx.datagrams, rx.payload_bytes, rx.frame_bytes) == (0, 70, 112)


def test_mdns_messages_tells_queries_from_responses(tmp_path: Path) -> None:
    query = b"\x00\x00\x00\x00" + b"\x00" * 8 + b"q"
    answer = b"\x00\x00\x84\x00" + b"\x00" * 8 + b"a" * 100
    p = pcap(
        tmp_path / "r1.pcap",
        [
            (1.0, frame(MINE, 5353, 5353, query)),
            (2.0, frame(MINE, 5353, 5353, answer)),
            (3.0, frame(OTHER, 5353, 5353, answer)),  # not ours
            (4.0, frame(MINE, 1900, 1900, answer)),  # not mDNS
        ],
    )
    got = mdns_messages(p, MINE, (0.0, 9.0))
    assert got == {"queries": 1, "responses": 1, "response_bytes": len(answer)}


def test_propagation_times_each_change_on_each_other_robot() -> None:
    ev: list[dict[str, Any]] = [
        {"t": 1.0, "op": "publish", "robot": "r1", "sid": "a"},
        {"t": 1.05, "op": "seen", "at": "r2", "robot": "r1", "sid": "a"},
        {"t": 1.7, "op": "seen", "at": "r3", "robot": "r1", "sid": "a"},  # late
        {"t": 2.0, "op": "publish", "robot": "r1", "sid": "b"},
        {"t": 2.1, "op": "unpublish", "robot": "r1", "sid": "b"},  # undone at once
        {"t": 3.0, "op": "unpublish", "robot": "r1", "sid": "a"},
        {"t": 3.02, "op": "gone", "at": "r2", "robot": "r1", "sid": "a"},
        {"t": 3.03, "op": "gone", "at": "r3", "robot": "r1", "sid": "a"},
        {"t": 9.8, "op": "publish", "robot": "r2", "sid": "c"},  # near the end
    ]
    got = propagation(ev, ["r1", "r2", "r3"], until=10.0)
    assert got["publish"]["count"] == 2 and got["publish"]["late"] == 1
    assert got["publish"]["p50_ms"] == pytest.approx(700.0)
    assert got["unpublish"]["count"] == 2 and got["unpublish"]["max_ms"] == pytest.approx(30.0)
    assert got["within_bound"] == {"publish": 0.5, "unpublish": 1.0}
    assert got["excluded"] == {"undone_within_bound": 2, "near_the_end": 1}
    # b was never seen but undone within the bound: not "never"; a robot not linked is left out
    never = propagation(ev, ["r1", "r2", "r3"], until=10.0, linked=lambda a, b, t: b == "r2")
    assert never["publish"]["count"] == 1 and never["publish"]["never"] == 0


def test_usage_is_cpu_share_and_memory_of_a_tree() -> None:
    readings = [Reading(0.0, 1.0, 10240), Reading(10.0, 1.5, 20480), Reading(20.0, 3.0, 15360)]
    got = usage(readings)
    assert got["cpu_percent"] == 10.0 and got["pss_mib_max"] == 20.0 and got["pss_mib_mean"] == 15.0
    assert usage(readings[:1]) == {"samples": 1}


def test_first_time_replays_the_watchers_notes() -> None:
    ev: list[dict[str, Any]] = [
        {"t": 1.0, "op": "publish", "robot": "r1", "sid": "a"},
        {"t": 1.2, "op": "seen", "at": "r2", "robot": "r1", "sid": "a"},
        {"t": 1.5, "op": "seen", "at": "r3", "robot": "r1", "sid": "a"},
        {"t": 5.0, "op": "gone", "at": "r2", "robot": "r1", "sid": "a"},
        {"t": 6.0, "op": "gone", "at": "r3", "robot": "r1", "sid": "a"},
    ]
    assert own_services(ev, "r1", 2.0) == {"a"}
    assert first_time(ev, 1.0, 9.0, everyone_lists(["r2", "r3"], {"r1": {"a"}})) == 0.5
    assert first_time(ev, 4.0, 9.0, nobody_lists(["r2", "r3"], ["r1"])) == 2.0
    assert first_time(ev, 4.0, 5.5, nobody_lists(["r2", "r3"], ["r1"])) is None
    exact = everyone_lists(["r2", "r3"], {"r1": {"a"}, "r2": set(), "r3": set()}, exact=True)
    assert first_time(ev, 0.0, 9.0, exact) == 1.5
    assert first_time(ev, 0.0, 9.0, halves_apart(["r1"], ["r2", "r3"])) == 0.0


def test_a_leave_is_timed_on_the_services_the_robot_had_and_an_older_ghost_is_apart() -> None:
    # r1 unpublished "old" at 2, but r2 listed it again (python-zeroconf: a goodbye overtook
    # an answer sent just before it); r1 leaves at 4 with "a".
    ev: list[dict[str, Any]] = [
        {"t": 1.0, "op": "publish", "robot": "r1", "sid": "a"},
        {"t": 1.0, "op": "publish", "robot": "r1", "sid": "old"},
        {"t": 1.2, "op": "seen", "at": "r2", "robot": "r1", "sid": "a"},
        {"t": 1.2, "op": "seen", "at": "r2", "robot": "r1", "sid": "old"},
        {"t": 2.0, "op": "unpublish", "robot": "r1", "sid": "old"},
        {"t": 2.1, "op": "gone", "at": "r2", "robot": "r1", "sid": "old"},
        {"t": 2.1, "op": "seen", "at": "r2", "robot": "r1", "sid": "old"},
        {"t": 4.3, "op": "gone", "at": "r2", "robot": "r1", "sid": "a"},
    ]
    had = own_services(ev, "r1", 4.0)
    assert had == {"a"}
    assert first_time(ev, 4.0, 9.0, nobody_lists_these(["r2"], "r1", had)) == 0.3
    assert first_time(ev, 4.0, 9.0, nobody_lists(["r2"], ["r1"])) is None
    assert replay(ev, 9.0) == {"r2": {("r1", "old")}}


def test_the_unpublish_scheduler_picks_a_published_service_once() -> None:
    board = Board(orders={i: threading.Event() for i in range(3)})
    rng = random.Random(1)
    assert board.pick(rng) is None
    board.published |= {0, 2}
    picked = {board.pick(rng), board.pick(rng)}
    assert picked == {0, 2} and board.pick(rng) is None
    assert board.orders[0].is_set() and board.orders[2].is_set() and not board.orders[1].is_set()


def test_zeroconf_instance_names_carry_robot_and_service() -> None:
    name = instance("r3", "p17x0000abcd")
    assert name.endswith(TYPE) and owner(name) == ("r3", "p17x0000abcd")
    assert owner("printer._ipp._tcp.local.") is None and owner(f"nobody.{TYPE}") is None


def test_the_docs_tables_say_what_each_run_measured_and_what_is_missing() -> None:
    from bench.paper_figures import markdown

    run = {
        "config": "static-6-70",
        "robots": 6,
        "latency": {
            "publish": {"p50_ms": 12.34, "p99_ms": 50.0},
            "unpublish": {"p50_ms": 8.0, "p99_ms": 30.0},
            "neighbors": {"p50_ms": {"mean": 4.0}, "p99_ms": {"max": 9.0}, "requests": 180_000},
        },
        "resources": {"cpu_percent": {"mean": 40.0}, "discovery_cpu_percent": {"mean": 0.5},
                      "pss_mib": {"mean": 35.0}},
        "traffic": {"per_5_min_kB": {"tx_payload": {"mean": 47.3}, "rx_payload": {"mean": 176.2}}},
        "seen_by_peers": {"within_bound": {"publish": 1.0, "unpublish": 0.995}},
    }  # fmt: skip
    failed = {"config": "static-2-30", "robots": 2, "latency": {}, "resources": {}}
    text = markdown({"mode": "full", "minutes_per_run": 5.0, "machine": {"nproc": 2},
                     "runs": [run, failed], "scale": [{"robots": 20, "traffic": {}}]})  # fmt: skip
    lines = text.splitlines()
    row = next(line for line in lines if line.startswith("| static-6-70"))
    # 180,000 answers over 5 minutes on 6 robots: 100 a second each
    assert row == (
        "| static-6-70 | 12.3 / 50.0 | 8.0 / 30.0 | 4.0 / 9.0 | 100 | 40.0 (0.50) | 35.0 "
        "| 47.3 | 176.2 | 100.0% / 99.5% |"
    )
    gap = next(line for line in lines if line.startswith("| static-2-30"))
    assert gap.count("—") == 14 and "None" not in gap
    assert any(line.startswith("| the paper") and "220-320 | 540-850" in line for line in lines)
    assert "| 20 | — | — | — | — |" in lines


def test_traffic_scales_each_robots_bytes_to_five_minutes(tmp_path: Path) -> None:
    """bench.paper's traffic table from a robot's pcap: its per-robot kB per 5 minutes, both
    ways and both sizes (what figure 6 is drawn from)."""
    from bench.paper import traffic

    pcap(
        tmp_path / "r1.pcap",
        [
            (10.0, frame(MINE, 1900, 1900, b"x" * 100)),
            (11.0, frame(OTHER, 1900, 1900, b"y" * 50)),
            (12.0, frame(MINE, 40000, 1900, b"w" * 10)),
        ],
    )
    got = traffic(tmp_path, ["r1"], {"r1": MINE}, (0.0, 300.0))
    assert got["per_robot"]["r1"]["per_5_min_kB"] == {
        "tx_payload": 0.11,
        "tx_frame": 0.19,
        "rx_payload": 0.05,
        "rx_frame": 0.09,
    }
    assert got["per_5_min_kB"]["tx_payload"]["mean"] == pytest.approx(0.11, abs=0.01)
