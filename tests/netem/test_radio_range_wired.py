"""radio-range on the wired medium (a bridge and its rules), in the netem tier's VM: the
figures the radio tier's runs of the same scenario (tests/radio/test_radio_scenarios.py) are
set beside in docs/fleet-behaviour.md, measured alike: the same kind of VM (one emulated
CPU, the same kernel), the scenario run the same way (quick, no plots, captures on every
robot), while the radio tier's VM runs beside it as `make test-vms` runs them.

It needs no radio, so it runs in the VM whose tier ends first (the netem tier's: about 4
minutes where the radio tier's takes over 20); here, where the kernel has no sch_netem, it
skips with the rest of the tier.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from netlab.doctor import capabilities
from tests.support.radio import run, startup_line, times_line

pytestmark = [pytest.mark.root, pytest.mark.netem]


def test_the_same_range_scenario_on_the_wired_medium_in_the_vm(tmp_path: Path) -> None:
    caps = capabilities()
    if not caps.netem:
        pytest.skip(
            f"runs in the netem tier's VM (`make test-netem`), beside the radio tier's: "
            f"{caps.why.get('netem', 'no sch_netem here')}"
        )
    result, report = run("radio-range", tmp_path / "run", medium="wired")
    assert report["meta"]["medium"] == "wired" and "air" not in report
    payload = {r: t["tx_kB"]["payload"] for r, t in report["traffic"]["robots"].items()}
    frames = {r: t["tx_kB"]["frame"] for r, t in report["traffic"]["robots"].items()}
    start = startup_line(result, report, joined=False)
    print(
        f"\nradio-range wired (the netem tier's VM): {start}; {times_line(result)}; run "
        f"{result.duration:.0f} s; SDfR payload sent (kB) {payload}; frames sent (kB) {frames}"
    )
