"""The bundled radio scenarios, run by the scenario engine as `netlab run NAME` runs them, on
802.11 radios in the radio tier's VM, with captures on every robot and on the air:

* radio-range in IBSS (WPA2), over netlab's own radio medium: 4 robots join the fleet's WiFi
  and list each other with their services, then one walks out of range (the medium stops
  delivering its frames, by the range model) and back, then a partition and a merge;
* radio-range in 802.11s mesh (SAE), over netlab's own radio medium, the same checks;
* radio-mobility in IBSS and in 802.11s mesh: 3 robots walk on random waypoints (the wired
  `mobility` scenario's hall and range) at a 2 s beacon, and the lists must agree with the
  medium's truth as there, a new link allowed 3 beacons instead of 1 (in mesh the truth
  links robots through a third that forwards);
and radio-range on the wired medium, for the comparison, runs in the netem tier's VM
(tests/netem/test_radio_range_wired.py).

Mesh peering in the emulated VM needed sdfrd's mesh timers (`sdfr.host.wifi.MESH_TIMERS`):
with wpa_supplicant's 40 ms ones a robot's peer links kept closing and reopening.

Each radio run's report says the medium was the radio and counts what went on the air
(802.11 management, EAPOL, data) per robot, by name.  The times measured (sdfrd's start to
healthy, i.e. the WiFi joined; then to every robot listing every other), the bytes on the air
and the medium's own cost are printed for docs/fleet-behaviour.md.  The VM emulates one slow
CPU: the scenarios' deadlines are generous.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from tests.support.radio import run, startup_line, times_line

pytestmark = pytest.mark.root


def medium_line(folder: Path) -> str:
    """The air medium's own counters (netlab.airmedium's stats, kept in the run's logs)."""
    stats = json.loads((folder / "logs" / "air-medium.json").read_text())
    per = stats["cpu_per_frame"] or 0.0
    return (
        f"medium ({stats['priority']}): {stats['frames']} frames, {stats['delivered']} copies, "
        f"{stats['acked']} of {stats['unicast']} unicast acked, {per * 1e3:.2f} ms CPU a frame, "
        f"{stats['behind']} of {stats['wakeups']} wake-ups behind (most {stats['max_batch']})"
    )


def air_line(report: dict[str, Any]) -> str:
    per = report["air"]["by_transmitter"]
    robots = {k: v for k, v in per.items() if k.startswith("r")}
    parts = []
    for robot, t in robots.items():
        kinds = ", ".join(f"{k} {v['bytes']} B" for k, v in t["by_kind"].items() if v["frames"])
        parts.append(f"{robot} {t['frames']} frames {t['bytes']} B ({kinds})")
    return "; ".join(parts)


def check_air(report: dict[str, Any], mode: str = "ibss") -> None:
    """What a radio run's report must say of the air (its medium, the robots by name)."""
    assert report["meta"]["medium"] == "radio"
    assert report["meta"]["air_medium"] == "netlab"
    air = report["air"]
    robots = [k for k in air["by_transmitter"] if k.startswith("r")]
    named = [f"r{i}" for i in range(1, report["meta"]["robots"] + 1)]
    assert robots == named, list(air["by_transmitter"])  # named, not MACs
    kinds = air["by_kind"]
    assert kinds["management"]["frames"] > 0 and kinds["data"]["frames"] > 0, kinds
    if mode == "ibss":
        assert kinds["eapol"]["frames"] > 0, kinds  # IBSS's WPA2 4-way handshakes
    else:  # mesh: SAE (authentication frames) and AMPE (action frames), no EAPOL
        assert kinds["eapol"]["frames"] == 0, kinds


def traffic_line(report: dict[str, Any]) -> str:
    air = report["air"]
    payload = {r: t["tx_kB"]["payload"] for r, t in report["traffic"]["robots"].items()}
    return (
        f"air: {air['frames']} frames, {air['bytes']} B in the run; {air_line(report)}; "
        f"SDfR payload sent (kB) {payload}"
    )


def test_a_robot_walks_out_of_range_and_back_then_a_partition_and_merge(tmp_path: Path) -> None:
    result, report = run("radio-range", tmp_path / "run", wifi_mode="ibss")
    check_air(report)
    stats = json.loads((tmp_path / "run" / "logs" / "air-medium.json").read_text())
    assert stats["frames"] > 0 and stats["delivered"] > 0 and stats["acked"] > 0, stats
    assert stats["unknown_sender"] == 0 and stats["send_errors"] == 0, stats
    assert stats["priority"] == "SCHED_FIFO 10", stats  # the air does not wait for the robots
    print(
        f"\nradio-range ibss: {startup_line(result, report)}; {times_line(result)}; run "
        f"{result.duration:.0f} s; {traffic_line(report)}; {medium_line(tmp_path / 'run')}"
    )


def test_the_range_scenario_in_mesh_mode(tmp_path: Path) -> None:
    """radio-range in 802.11s mesh (SAE and AMPE peering) over netlab's medium: the same
    checks and deadlines as in IBSS. r4 out of range has no mesh path to the others (no peer
    in range to forward through), so it drops out as in IBSS."""
    result, report = run("radio-range", tmp_path / "run", wifi_mode="mesh")
    check_air(report, "mesh")
    print(
        f"\nradio-range mesh: {startup_line(result, report)}; {times_line(result)}; run "
        f"{result.duration:.0f} s; {traffic_line(report)}; {medium_line(tmp_path / 'run')}"
    )


@pytest.mark.parametrize("mode", ["ibss", "mesh"])
def test_robots_walking_over_the_air_keep_lists_that_agree_with_the_medium(
    tmp_path: Path, mode: str
) -> None:
    """radio-mobility over netlab's medium, in IBSS and in 802.11s mesh: 3 robots on random
    waypoints (2 s beacon), links coming and going by the range model; once settled, the
    lists agree with the medium by the wired `mobility` scenario's two checks, with the
    air's longer lag for new links. In mesh the radios forward each other's frames, so the
    medium's truth links two robots out of range through a third in range of both
    (`Lab.links`, `netlab.ranges.forwarded`)."""
    result, report = run("radio-mobility", tmp_path / "run", wifi_mode=mode)
    check_air(report, mode)
    agreement = "; ".join(c.detail for c in result.checks if c.kind == "agreement")
    air = report["air"]  # the air only is captured: its data frames are encrypted
    print(
        f"\nradio-mobility {mode}: {startup_line(result, report)}; {agreement}; run "
        f"{result.duration:.0f} s; air: {air['frames']} frames, {air['bytes']} B; "
        f"{air_line(report)}; {medium_line(tmp_path / 'run')}"
    )
