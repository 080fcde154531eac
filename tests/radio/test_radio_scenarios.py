"""The bundled radio scenarios, run by the scenario engine as `netlab run NAME` runs them, on
802.11 radios in the radio tier's VM:

* radio-startup, in IBSS (WPA2): 4 robots join the fleet's WiFi and list each other with
  their services; the run's report says the medium was the radio and counts what went on the
  air (802.11 management, EAPOL, data) per robot (the mesh's join and discovery are
  test_radio_join.py's; the tier's time is kept down);
* radio-range: a robot walks out of range (the lab's own radio medium stops delivering its
  frames, by the range model) and back, then a partition and a merge.

The times measured (from sdfrd's start to healthy, i.e. the WiFi joined, and to every robot
listing every other) and the bytes on the air are printed for docs/fleet-behaviour.md.  The
VM emulates one slow CPU: the scenarios' deadlines are generous.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from netlab import scenario

pytestmark = pytest.mark.root


def run(name: str, folder: Path, **sdfrd: Any) -> tuple[scenario.RunResult, dict[str, Any]]:
    sc = scenario.load(scenario.find(name))
    if sdfrd:
        sc = replace(sc, sdfrd={**sc.sdfrd, **sdfrd})
    result = scenario.run(sc, run_dir=folder, quick=True)
    assert result.ok, "\n".join([f"scenario {name} {result.status}:", *result.summary()])
    report = json.loads((folder / "report.json").read_text())
    return result, report


def air_line(report: dict[str, Any]) -> str:
    per = report["air"]["by_transmitter"]
    robots = {k: v for k, v in per.items() if k.startswith("r")}
    parts = []
    for robot, t in robots.items():
        kinds = ", ".join(f"{k} {v['bytes']} B" for k, v in t["by_kind"].items() if v["frames"])
        parts.append(f"{robot} {t['frames']} frames {t['bytes']} B ({kinds})")
    return "; ".join(parts)


@pytest.mark.parametrize("mode", ["ibss"])  # (mesh's join and discovery: test_radio_join.py)
def test_four_robots_start_up_over_the_air(mode: str, tmp_path: Path) -> None:
    result, report = run("radio-startup", tmp_path / "run", wifi_mode=mode)
    assert report["meta"]["medium"] == "radio"
    air = report["air"]
    robots = [k for k in air["by_transmitter"] if k.startswith("r")]
    assert robots == ["r1", "r2", "r3", "r4"], list(air["by_transmitter"])  # named, not MACs
    kinds = air["by_kind"]
    assert kinds["management"]["frames"] > 0 and kinds["data"]["frames"] > 0, kinds
    if mode == "ibss":  # WPA2's 4-way handshake (mesh keys itself with SAE and AMPE instead)
        assert kinds["eapol"]["frames"] > 0, kinds
    meta_steps = report["meta"]["steps"]
    start = meta_steps[0]["end"] - meta_steps[0]["start"]
    listed = next(c for c in result.checks if c.kind == "lists")
    payload = {r: t["tx_kB"]["payload"] for r, t in report["traffic"]["robots"].items()}
    print(
        f"\nradio-startup {mode}: sdfrd healthy (WiFi joined) on 4 in {start:.1f} s, all list "
        f"all {listed.took:.1f} s later; run {result.duration:.0f} s; air: {air['frames']} "
        f"frames, {air['bytes']} B; {air_line(report)}; SDfR payload sent (kB) {payload}"
    )


def test_a_robot_walks_out_of_range_and_back_then_a_partition_and_merge(tmp_path: Path) -> None:
    result, report = run("radio-range", tmp_path / "run", wifi_mode="ibss")
    took = {c.description: c.took for c in result.checks}
    assert report["meta"]["medium"] == "radio" and report["air"]["frames"] > 0
    print("\nradio-range ibss: " + "; ".join(f"{k}: {v:.1f} s" for k, v in took.items() if v))
