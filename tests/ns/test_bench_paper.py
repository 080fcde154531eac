"""`make bench-paper` in CI: every part of the bench for seconds (`--smoke`), so it cannot rot.

The static and dynamic runs, python-zeroconf beside SDfR and the growth run, each for a few
seconds, then the figures: the run must end well, every measure be there and plausible, and
every figure drawn.  Its numbers mean nothing (seconds of load; the side-by-side at a 1 s
beacon): `make bench-paper` takes the real ones.  About 3-4 minutes.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.root


@pytest.fixture(scope="module")
def smoke(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    runs = tmp_path_factory.mktemp("bench-paper")
    out = runs / "bench-paper.json"
    res = subprocess.run(
        [sys.executable, "-m", "bench.paper", "--smoke", "--runs", str(runs), "--out", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    print(res.stderr[-3000:])
    assert res.returncode == 0, res.stderr[-3000:]
    result: dict[str, Any] = json.loads(out.read_text())
    return result


def test_the_paper_runs_measure_what_its_figures_show(smoke: dict[str, Any]) -> None:
    assert smoke["mode"] == "smoke" and not smoke["problems"]
    assert [r["config"] for r in smoke["runs"]] == ["static-2-30", "dynamic-6-70"]
    for run in smoke["runs"]:
        lat = run["latency"]
        assert lat["publish"]["count"] >= 30 and lat["publish"]["p50_ms"] > 0
        assert lat["neighbors"]["requests"] > 100
        for robot in run["resources"]["per_robot"].values():
            assert robot["cpu_percent"] > 0 and robot["pss_mib_max"] > 10
            assert {"api", "discovery", "supervisor"} <= set(robot["layers"])
        traffic = run["traffic"]["per_5_min_kB"]
        assert traffic["tx_payload"]["min"] > 0 and traffic["rx_frame"]["min"] > 0
        assert traffic["tx_frame"]["min"] > traffic["tx_payload"]["min"]
        assert run["traffic"]["by_type_tx_kB_per_robot_5_min"]
        assert run["seen_by_peers"]["publish"]["count"] > 0
        for when in ("conditions_before", "conditions_after"):
            assert len(run[when]["loadavg_1_5_15"]) == 3
    assert smoke["scale"][0]["robots"] == 2 and smoke["scale"][0]["load"]["consumers"] == 0


def test_sdfr_python_zeroconf_and_zenoh_side_by_side(smoke: dict[str, Any]) -> None:
    side = smoke["side_by_side"]
    systems = ("sdfr", "zeroconf", "zenoh")
    assert tuple(side["systems"]) == systems
    rows = {row["measure"].split(" (")[0]: row for row in side["table"]}
    for measure in (
        "start-up: all robots list all services",
        "a new service seen on all peers",
        "a graceful leave seen on all peers",
    ):
        for system in systems:
            assert rows[measure][system] is not None, (measure, system)
    # A 1 s beacon: a silent death is seen within its 3 beacons; to Zenoh a kill -9 closes
    # TCP sessions (seen at once), and a partition is its silent departure: its 10 s lease is
    # longer than the smoke's partition, so only SDfR's halves must have dropped each other.
    assert rows["a kill -9 seen on all peers"]["sdfr"] is not None
    assert rows["a kill -9 seen on all peers"]["zenoh"] is not None
    assert rows["6 s partition: each half stops listing the other"]["sdfr"] is not None
    for system in systems:
        assert side["traffic"]["per_5_min_kB"][system]["tx_payload"]["min"] > 0, system
        assert side["traffic"]["tx_datagrams_per_s"][system]["min"] > 0, system
        assert side["resources"][system]["pss_mib"]["min"] > 0, system
    # Zenoh's sessions are TCP: its bytes are counted (not only its UDP scouting).
    assert side["traffic"]["flows"]["zenoh"] == ["udp 7446", "tcp 7447"]


def test_every_figure_is_drawn_with_its_data(smoke: dict[str, Any]) -> None:
    figs = smoke["figures"]
    for key in ("json", "fig4", "fig5", "fig6", "growth"):
        assert Path(figs[key]).stat().st_size > 1000, key
    data = json.loads(Path(figs["json"]).read_text())
    assert data["fig6"]["paper"] == {"tx_kB": [220.0, 320.0], "rx_kB": [540.0, 850.0]}
    assert len(data["fig4"]["ours"]["publish_p50"]) == 2
    assert data["side_by_side"]
