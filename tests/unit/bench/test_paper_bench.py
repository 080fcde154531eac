"""The paper bench's pure parts: bytes from pcaps, how long changes took to be seen, what the
side-by-side makes of its watchers' notes, and the load's unpublish scheduler."""

from __future__ import annotations

import random
import struct
import threading
from pathlib import Path
from typing import Any

import pytest

from bench.listed import (
    everyone_lists,
    first_time,
    halves_apart,
    nobody_lists,
    nobody_lists_these,
    own_services,
    replay,
)
from bench.paper_load import Board
from bench.paper_measure import (
    Reading,
    ip_traffic,
    mdns_messages,
    propagation,
    udp_traffic,
    usage,
)
from bench.peers import LATER_FRAGMENTS, capture_filter
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


def tcp_frame(src_mac: str, sport: int, dport: int, payload: bytes, options: int = 0) -> bytes:
    eth = bytes.fromhex(("020000000009" + src_mac.replace(":", "")) + "0800")
    tcp = struct.pack("!HHIIBBHHH", sport, dport, 1, 1, (5 + options) << 4, 0x18, 512, 0, 0)
    tcp += b"\x01" * 4 * options + payload
    ip = struct.pack(
        "!BBHHHBBH4s4s", 0x45, 0, 20 + len(tcp), 0, 0, 64, 6, 0, b"\n\x01\x00\x01",
        b"\n\x01\x00\x02",
    )  # fmt: skip
    return eth + ip + tcp


def test_ip_traffic_counts_tcp_segments_and_udp_datagrams_apart(tmp_path: Path) -> None:
    p = pcap(
        tmp_path / "r1.pcap",
        [
            (10.0, tcp_frame(MINE, 7447, 50000, b"x" * 100, options=3)),  # 12 bytes of options
            (10.5, tcp_frame(OTHER, 50000, 7447, b"")),  # a pure ACK
            (11.0, tcp_frame(OTHER, 50001, 7447, b"y" * 30)),
            (11.5, frame(MINE, 7447, 7447, b"u" * 20)),  # UDP 7447: not TCP 7447
            (12.0, tcp_frame(MINE, 40000, 8000, b"other port")),
        ],
    )
    got = ip_traffic(p, MINE, [("tcp", 7447), ("udp", 7447)], (9.0, 20.0))
    tcp, udp = got[("tcp", 7447)], got[("udp", 7447)]
    assert (tcp.tx.datagrams, tcp.tx.payload_bytes, tcp.tx.frame_bytes) == (1, 100, 166)
    assert (tcp.rx.datagrams, tcp.rx.payload_bytes) == (2, 30)
    assert (udp.tx.datagrams, udp.tx.payload_bytes, udp.rx.datagrams) == (1, 20, 0)


def fragments(src_mac: str, ident: int, dport: int, payload: bytes) -> list[bytes]:
    """One UDP datagram to `dport`, IP-fragmented into frames of 1500 bytes of IP at most."""
    eth = bytes.fromhex(("01005e7f0001" + src_mac.replace(":", "")) + "0800")
    udp = struct.pack("!HHHH", 40000, dport, 8 + len(payload), 0) + payload
    out = []
    for at in range(0, len(udp), 1480):
        piece = udp[at : at + 1480]
        flags = (0x2000 if at + 1480 < len(udp) else 0) | at // 8
        ip = struct.pack(
            "!BBHHHBBH4s4s", 0x45, 0, 20 + len(piece), ident, flags, 1, 17, 0,
            b"\n\x01\x00\x01", b"\xef\xff\x00\x01",
        )  # fmt: skip
        out.append(eth + ip + piece)
    return out


def test_a_fragmented_datagram_counts_once_with_all_its_frames(tmp_path: Path) -> None:
    # 3000 bytes to UDP 7400 in three frames; the later two carry no UDP header (their bytes
    # even read as port 7400), and a stray later fragment of another datagram counts nowhere.
    sent = fragments(MINE, 7, 7400, (b"\x1c\xe8" * 1500))
    stray = fragments(MINE, 8, 7400, b"s" * 2000)[1]
    assert len(sent) == 3 and capture_filter([("udp", 7400)]).endswith(LATER_FRAGMENTS)
    p = pcap(tmp_path / "r1.pcap", [(10.0 + i, f) for i, f in enumerate([*sent, stray])])
    tx = ip_traffic(p, MINE, [("udp", 7400)], (9.0, 20.0))[("udp", 7400)].tx
    assert (tx.datagrams, tx.payload_bytes) == (1, 3000)
    assert tx.frame_bytes == sum(len(f) for f in sent)


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


def test_the_side_by_side_table_has_a_column_and_a_ratio_per_system() -> None:
    from bench.peers_report import markdown, table

    result: dict[str, Any] = {
        "robots": 6, "publishers_per_robot": 70, "kill_cap_s": 120.0, "partition_s": 40.0,
        "timing_s": {"after_merge": 60.0, "loss": 10.0},  # netlab's pair loss: in %
        "systems": {"sdfr": {"label": "SDfR 0.2.0", "knob": "its defaults (beacon 10 s)"},
                    "zeroconf": {"label": "python-zeroconf 0.154", "knob": "its defaults"},
                    "zenoh": {"label": "Zenoh 1.1", "knob": "its defaults (lease 10 s)"}},
        "startup_s": {"sdfr": 2.0, "zeroconf": 5.0, "zenoh": None},
        "kill_9_s": {"sdfr": 25.0, "zeroconf": None, "zenoh": 0.0},
        "stale_after_leave": {"sdfr": [], "zeroconf": [["r1", "p3x1"]], "zenoh": []},
        "traffic": {"flows": {"sdfr": ["udp 1900"], "zeroconf": ["udp 5353"],
                              "zenoh": ["udp 7446", "tcp 7447"]},
                    "per_5_min_kB": {"sdfr": {"tx_payload": {"mean": 10.0}},
                                     "zenoh": {"tx_payload": {"mean": 25.0}}}},
    }  # fmt: skip
    result["table"] = rows = table(result)
    by = {row["measure"].split(" (")[0]: row for row in rows}
    start = by["start-up: all robots list all services"]
    assert (start["sdfr"], start["zeroconf"], start["zenoh"]) == (2.0, 5.0, None)
    assert start["ratio"] == {"zeroconf": 2.5}  # no ratio to a value not measured
    tx = next(row for row in rows if row["measure"].startswith("TX kB per robot per 5 min (pay"))
    assert tx["ratio"] == {"zenoh": 2.5}
    kill = by["a kill -9 seen on all peers"]
    assert "Zenoh 1.1: the kernel closes" in kill["note"] and "zeroconf" not in kill["note"]
    assert "python-zeroconf 0.154 1" in by["a graceful leave seen on all peers"]["note"]
    lines = markdown(result)
    assert lines[0].startswith("Side by side, one lab of 6 robots on 10 % loss on every pair, ")
    assert lines[2] == (
        "| measure | SDfR 0.2.0 | python-zeroconf 0.154 | Zenoh 1.1 | python-zeroconf 0.154 ÷ "
        "SDfR | Zenoh 1.1 ÷ SDfR | note |"
    )
    assert lines[3].count("---") == 7
    start_line = next(line for line in lines if line.startswith("| start-up"))
    assert "| 2.00 | 5.00 | not seen | 2.50 | — |" in start_line


def test_a_peer_unknown_or_not_installed_is_refused_by_name() -> None:
    from bench.peers import PEERS, Peer, chosen

    assert [p.name for p in chosen(["zenoh", "zeroconf"])] == ["zenoh", "zeroconf"]
    with pytest.raises(ValueError, match="no peer 'cyclone': the side-by-side knows zeroconf, "):
        chosen(["cyclone"])
    ghost = Peer("ghost", "Ghost", "bench.ghost", (("udp", 1),), "ghost-dist", "no_such_module")
    assert ghost.missing() == "Ghost: ghost-dist is not installed (pip install -e '.[dev]')"
    assert ghost.version() == "?"
    assert capture_filter(PEERS["zenoh"].flows) == (
        f"udp port 7446 or tcp port 7447 or {LATER_FRAGMENTS}"
    )
    # Two Zenoh fleets in one lab must not hear each other: their ports differ.
    assert not set(PEERS["zenoh"].flows) & set(PEERS["zenoh-lease2s"].flows)


def test_the_events_watcher_follows_each_robot_change_and_reads_the_list_when_told_little() -> None:
    from bench.paper_load import after

    seen = {("r2", "a"), ("r3", "b")}
    got = after(seen, "robot.appeared", "r4", {"services": [{"id": "c"}, {"id": "d"}]})
    assert got == seen | {("r4", "c"), ("r4", "d")}
    moved = after(seen, "robot.services", "r2", {"added": [{"id": "e"}], "removed": ["a"]})
    assert moved == {("r2", "e"), ("r3", "b")}
    for gone in ("robot.left", "robot.unreachable", "robot.forgotten"):
        assert after(seen, gone, "r3", {}) == {("r2", "a")}
    assert after(seen, "robot.indicator", "r2", {"indicator": 0.5}) == seen
    # Too many services to carry, or events lost: the watcher must read the whole list.
    assert after(seen, "robot.services", "r2", {"added_truncated": True, "removed": []}) is None
    assert after(seen, "resync", "None", {}) is None
    assert seen == {("r2", "a"), ("r3", "b")}  # never changed in place


def test_the_bytes_figure_draws_a_line_per_system_and_loss(tmp_path: Path) -> None:
    from bench.peers_report import floor_line, growth_figure

    def result(n: int, loss: float, sdfr_kb: float) -> dict[str, Any]:
        return {
            "robots": n,
            "timing_s": {"loss": loss},
            "systems": {"sdfr": {"label": "SDfR"}, "zenoh": {"label": "Zenoh"}},
            "traffic": {"per_5_min_kB": {
                "sdfr": {"tx_frame": {"mean": sdfr_kb}, "rx_frame": {"mean": 5 * sdfr_kb}},
                "zenoh": {"tx_frame": {"mean": 90.0}},  # its rx not measured: left out
            }},
            "floor": {"idle": {"from": "r1", "to": "r2", "p50_ms": 0.08, "p99_ms": 0.2,
                               "sent": 200, "arrived": 200}},
        }  # fmt: skip

    runs = [result(6, 0.0, 40.0), result(20, 0.0, 60.0), result(6, 10.0, 45.0)]
    path = growth_figure(runs, tmp_path / "bytes.png")
    assert path.read_bytes()[:4] == b"\x89PNG" and path.stat().st_size > 10_000
    line = floor_line(runs[0])
    assert line == ["The floor, a bare multicast datagram r1 to r2: before the systems started "
                    "p50 0.08 ms, p99 0.20 ms (200 of 200 arrived)."]  # fmt: skip


def test_the_side_by_side_takes_sizes_and_losses_as_lists_and_says_what_is_wrong() -> None:
    import argparse

    from bench.side_by_side import numbers

    assert numbers(int)("6,20") == [6, 20] and numbers(float)("0,10") == [0.0, 10.0]
    with pytest.raises(argparse.ArgumentTypeError, match="'6,x': not a comma-separated list"):
        numbers(int)("6,x")
