"""Address self-configuration with real daemons in netlab (needs root)."""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from ipaddress import IPv4Address
from pathlib import Path
from typing import Any

import pytest

from netlab.analysis import arp_counts_by_sender
from netlab.capture import Capture
from netlab.lab import Lab
from netlab.pcap import read_run
from sdfr.protocol.addressing import candidates
from tests.support.waiting import poll

pytestmark = pytest.mark.root

BEACON = 1.0
FLEET = 1


def derived(mac: str) -> str:
    return str(next(candidates(FLEET, mac)))


@pytest.fixture
def lab(lab_factory: Callable[..., Lab], tmp_path: Path) -> Lab:
    return lab_factory(seed=3, workdir=tmp_path / "lab", addressing="auto")


def listing(lab: Lab, robot: str) -> dict[str, dict[str, Any]]:
    return {n["robot_id"]: n for n in lab.client(robot).neighbors()}


def test_six_robots_take_their_derived_addresses_and_discover(lab: Lab) -> None:
    names = [f"r{i}" for i in range(1, 7)]
    for name in names:
        lab.add_robot(name)
    lab.start_all(beacon_interval=BEACON)
    for name in names:
        mac = lab.robot(name).mac
        poll(
            f"{name} holds {derived(mac)}",
            lambda n=name, m=mac: lab.live_addresses(n) == [derived(m)],
            3.0,
        )
    want = {n: derived(lab.robot(n).mac) for n in names}

    def all_listed() -> bool:
        for a in names:
            seen = {r: n["address"] for r, n in listing(lab, a).items()}
            if seen != {b: want[b] for b in names if b != a}:
                return False
        return True

    poll("every robot lists every other at its derived address", all_listed, 3.0)


def test_merge_conflict_one_moves_services_kept(lab: Lab, tmp_path: Path) -> None:
    # Different MACs ending alike derive the same first address; the lower MAC keeps it.
    low, high = "02:00:00:00:12:34", "02:aa:00:00:12:34"
    shared = derived(low)
    assert derived(high) == shared
    lab.add_robot("r1", mac=low)
    lab.add_robot("r2", mac=high)
    lab.add_robot("r3")
    lab.add_robot("r4")
    lab.partition([["r1", "r3"], ["r2", "r4"]])
    captures = [
        Capture(lab.robot(r).ns, "eth0", tmp_path / f"{r}.pcap", bpf="arp", label=r)
        for r in ("r1", "r2")
    ]
    for c in captures:
        c.start()
    try:
        lab.start_all(beacon_interval=BEACON)
        poll(
            "r1 and r2 each hold the shared address in their partition",
            lambda: lab.live_addresses("r1") == [shared] == lab.live_addresses("r2"),
            3.0,
        )
        lab.client("r1").publish("map", "slam.map")
        lab.client("r2").publish("arm", "actuator.arm")
        poll("r3 lists r1's map", lambda: "r1" in listing(lab, "r3"), 3.0)
        merged = time.time()
        lab.merge()

        def resolved() -> bool:
            mine, theirs = lab.live_addresses("r1"), lab.live_addresses("r2")
            return mine == [shared] and len(theirs) == 1 and theirs != [shared]

        took = poll("conflict resolved: r1 keeps the address, r2 moves", resolved, 3.0)
        assert took <= 3.0
        moved = lab.live_addresses("r2")[0]
        assert IPv4Address(moved) in itertools.islice(candidates(FLEET, high), 5)
        expect = {"r1": (shared, {"map"}), "r2": (moved, {"arm"})}

        def everyone_sees_both() -> str | bool:
            """True, or what is still wrong (the poll's failure message shows it)."""
            wrong = []
            for observer in ("r1", "r2", "r3", "r4"):
                seen = listing(lab, observer)
                for robot, (addr, services) in expect.items():
                    if robot == observer:
                        continue
                    entry = seen.get(robot)
                    got = (
                        None
                        if entry is None
                        else (entry["address"], {s["name"] for s in entry["services"]})
                    )
                    if got != (addr, services):
                        wrong.append(f"{observer} lists {robot} as {got}, not {(addr, services)}")
            return True if not wrong else "; ".join(wrong)

        poll(
            "every robot lists r1 and r2 at their addresses with their services",
            everyone_sees_both,
            2.0,
        )
        assert [s["name"] for s in lab.client("r2").services()] == ["arm"]
        poll(
            "r2's /self shows its new address",
            lambda: lab.client("r2").self_info()["address"] == moved,
            2.0,
        )
    finally:
        for c in captures:
            c.stop()
    records = read_run(tmp_path)
    # Probes (for the new address, from 0.0.0.0) and announcements (sender = target) after
    # the merge. At most: each robot announces once on meeting new robots and once to
    # defend (4); r2 probes its next address 3 times, announces it twice, and once more on
    # meeting the robots again from it (6). The kernels' ordinary ARP requests and
    # replies (from 0.0.0.0 too while r2 has no address) are not part of it.
    sent = [r for r in records if r.kind == "arp" and r.direction == "tx" and r.time >= merged]
    probes = [r for r in sent if r.arp_op == 1 and r.src == "0.0.0.0" and r.dst == moved]
    announcements = [r for r in sent if r.arp_op == 1 and r.src == r.dst]
    story = [(round(r.time - merged, 3), r.capture, r.arp_op, r.src, r.dst) for r in sent]
    assert len(probes) == 3 and all(r.capture == "r2" for r in probes), story
    assert moved in {r.src for r in announcements}, story
    assert len(probes) + len(announcements) <= 10, story
    assert arp_counts_by_sender(records)


def test_a_robot_started_onto_a_held_address_never_takes_it(lab: Lab, tmp_path: Path) -> None:
    holder_mac, late_mac = "02:aa:00:00:12:34", "02:00:00:00:12:34"  # the late one is lower
    shared = derived(holder_mac)
    lab.add_robot("r1", mac=holder_mac)
    lab.add_robot("r2", mac=late_mac)
    lab.start("r1", beacon_interval=BEACON)
    poll("r1 holds its address", lambda: lab.live_addresses("r1") == [shared], 3.0)
    cap = Capture(lab.robot("r2").ns, "eth0", tmp_path / "r2.pcap", bpf="arp", label="r2")
    cap.start()
    try:
        lab.start("r2", beacon_interval=BEACON)
        poll("r2 holds an address", lambda: lab.live_addresses("r2") != [], 3.0)
    finally:
        cap.stop()
    assert lab.live_addresses("r1") == [shared]
    assert lab.live_addresses("r2") not in ([], [shared])
    mac = lab.robot("r2").mac
    claimed = [
        r.src
        for r in read_run(tmp_path)
        if r.kind == "arp" and r.src_mac == mac and r.src not in (None, "0.0.0.0")
    ]
    assert claimed and shared not in claimed  # it announced its own address, never the held one
