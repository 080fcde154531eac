"""The radio lab's own medium (`netlab.airmedium`): the radios hear each other by netlab's
range model, so a robot moved out of range, or cut off by a partition, drops out of the
others' lists over the air, and comes back when moved back or merged.

Runs in the radio tier's VM (scripts/vm.sh radio), one slow emulated CPU: the deadlines
are generous, the times measured and the medium's cost (its own counters) are printed.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from netlab import airmedium, naming
from netlab.lab import Lab
from netlab.ranges import UnitDisc
from sdfr.protocol.config import MISS_LIMIT
from tests.support.radio import listed, wait_until

pytestmark = pytest.mark.root

ROBOTS = ("r1", "r2", "r3")
FLEET = 8
RADIUS = 20.0
BEACON = 1.0
NEAR = {"r1": (0.0, 0.0), "r2": (10.0, 0.0), "r3": (15.0, 0.0)}
FAR = (100.0, 0.0)  # out of everyone's range
#: A robot's start under emulation (PBKDF2 in pure Python, wpa_supplicant), and the first join.
START = 240.0
DISCOVER = 120.0
#: A peer is unlisted after MISS_LIMIT silent beacon periods; ten times that under emulation.
LEAVE = 10 * MISS_LIMIT * BEACON
#: Back in range, the radios meet again (IBSS merge, a new key handshake if the stations
#: expired), then sdfrd's beacons: slower than leaving.
REJOIN = 180.0


@pytest.fixture
def lab(tmp_path: Path) -> Iterator[Lab]:
    with Lab(
        naming.unique_lab_name("m"),
        workdir=tmp_path / "lab",
        fleet=FLEET,
        air="radio",
        range_model=UnitDisc(RADIUS),
    ) as lab:
        yield lab


def all_listed(lab: Lab) -> bool:
    return all(listed(lab, r) == set(ROBOTS) - {r} for r in ROBOTS)


def r3_cut_off(lab: Lab) -> bool:
    return listed(lab, "r3") == set() and all("r3" not in listed(lab, r) for r in ("r1", "r2"))


def r1_r2_only(lab: Lab) -> bool:
    return listed(lab, "r1") == {"r2"} and listed(lab, "r2") == {"r1"}


def lapses(lab: Lab) -> int:
    """How often r1 and r2 found each other unreachable (their logs): a lapse of the link
    that stays (the emulated VM's load delays pings past their timeout at times)."""
    return sum(
        lab.robot(a).log.read_text().count(f"robot {b} unreachable")
        for a, b in (("r1", "r2"), ("r2", "r1"))
    )


def test_a_robot_out_of_range_or_partitioned_off_drops_out_and_comes_back(lab: Lab) -> None:
    """r1-r3 in range list each other; r3 moved out of range (the lab's radius) is unlisted
    by r1 and r2 and lists nobody while r1 and r2 keep each other; moved back, all list each
    other again; a partition and a merge the same.  The medium handled every frame, knew
    every sender and acknowledged unicast frames."""
    lab.add_robots(ROBOTS, NEAR)
    lab.start_all(ROBOTS, timeout=START, wifi_mode="ibss", beacon_interval=BEACON)
    lapsed: dict[str, int] = {}
    took = {"join": wait_until("r1-r3 each list the two others", lambda: all_listed(lab), DISCOVER)}

    lab.move("r3", FAR)
    assert ("r1", "r3") not in lab.links() and ("r1", "r2") in lab.links()
    assert airmedium.read_links(lab.air_links_file).links == lab.links()
    lapsed["out of range"] = lapses(lab)
    took["out of range"] = wait_until(
        "r3 is unlisted, lists nobody", lambda: r3_cut_off(lab), LEAVE
    )
    wait_until("r1 and r2 list each other (only)", lambda: r1_r2_only(lab), LEAVE)

    lab.move("r3", NEAR["r3"])
    lapsed["back in range"] = lapses(lab)
    took["back in range"] = wait_until("all list each other again", lambda: all_listed(lab), REJOIN)

    lab.partition([["r1", "r2"], ["r3"]])
    assert airmedium.read_links(lab.air_links_file).links == lab.links()
    lapsed["partition"] = lapses(lab)
    took["partition"] = wait_until("r3 is cut off by the partition", lambda: r3_cut_off(lab), LEAVE)
    wait_until("r1 and r2 list each other (only)", lambda: r1_r2_only(lab), LEAVE)

    lab.merge()
    lapsed["merge"] = lapses(lab)
    took["merge"] = wait_until(
        "all list each other after the merge", lambda: all_listed(lab), REJOIN
    )

    time.sleep(airmedium.STATS_EVERY + 1.0)  # its latest counters
    stats = airmedium.read_stats(lab.air_stats_file)
    print(
        f"\nradio medium ibss: seconds until {', '.join(f'{k} {v:.1f}' for k, v in took.items())}"
    )
    print(
        f"radio medium cost: {stats['frames']} frames ({stats['group']} group, "
        f"{stats['unicast']} unicast, {stats['acked']} acked) in {stats['seconds']:.0f} s, "
        f"{stats['delivered']} copies delivered, {stats['cpu_seconds']:.2f} CPU s = "
        f"{1e6 * stats['cpu_per_frame']:.0f} us per frame; "
        f"{stats['frames'] / stats['seconds']:.1f} frames/s"
    )
    print(f"r1/r2 lapses of their link before each step: {lapsed}, at the end {lapses(lab)}")
    print(f"radio medium counters: {stats}")
    assert stats["frames"] > 0 and stats["delivered"] > 0 and stats["acked"] > 0, stats
    assert stats["unknown_sender"] == 0 and stats["send_errors"] == 0, stats
