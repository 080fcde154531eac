"""bench/change_path.py: a change's parts, followed through the pcaps' records and the
loader's and watcher's notes."""

from __future__ import annotations

from bench import change_path
from bench.change_path import Timeline
from netlab.pcap import Record

R1, R2 = "10.0.0.1", "10.0.0.2"


def rec(t: float, direction: str, msg: str, src: str, dst: str, seq: int | None = None) -> Record:
    return Record(
        time=t, capture="", direction=direction, kind="sdfr", src_mac="", dst_mac="",
        src=src, dst=dst, multicast=dst.startswith("239."), frame_len=100, msg_type=msg, seq=seq,
    )  # fmt: skip


def test_a_change_splits_into_its_parts_and_one_not_challenged_counts_in_total_only() -> None:
    r1 = Timeline([
        rec(99.0, "tx", "Alive", R1, "239.255.255.250"),  # before the change: not its Update
        rec(100.006, "tx", "Update", R1, "239.255.255.250"),
        rec(100.0075, "rx", "Discovery", R2, R1, seq=5),
        rec(100.0076, "tx", "Response", R1, R2, seq=5),
        rec(100.030, "tx", "Update", R1, "239.255.255.250"),
    ])  # fmt: skip
    r2 = Timeline([
        rec(100.0061, "rx", "Update", R1, "239.255.255.250"),
        rec(100.007, "tx", "Discovery", R2, R1, seq=5),  # the challenge
        rec(100.008, "rx", "Response", R1, R2, seq=5),  # its answer
        rec(100.0301, "rx", "Update", R1, "239.255.255.250"),  # not challenged again
        rec(100.031, "tx", "Discovery", R2, "10.0.0.9", seq=6),  # a ping to someone else
    ])  # fmt: skip
    publishes = [
        {"asked": 100.0, "t": 100.004, "sid": "a"},
        {"asked": 100.025, "t": 100.028, "sid": "b"},
        {"asked": 100.5, "t": 100.504, "sid": "never-seen"},
    ]
    seen = {("r2", "a"): 100.011, ("r2", "b"): 100.034}
    parts = change_path.follow("r1", publishes, seen, {"r1": r1, "r2": r2}, {"r1": R1, "r2": R2})
    ms = {k: [round(1e3 * x, 3) for x in v] for k, v in parts.items()}
    assert ms == {
        "request": [4.0], "announced": [6.0], "carried": [0.1], "challenged": [0.9],
        "answered": [1.0], "told": [3.0], "total": [11.0, 9.0],
    }  # fmt: skip
    summary = change_path.summary(parts)
    assert summary["total"]["count"] == 2 and summary["told"]["p50_ms"] == 3.0
    (said,) = change_path.sentence(summary)
    assert said.startswith("SDfR's change path, p50 / p99 ms") and "told 3.0 / 3.0" in said
    assert change_path.sentence({}) == []
