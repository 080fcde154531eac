"""A fleet's bytes at the product's beacon, open and keyed: start-up and steady state."""

from __future__ import annotations

import statistics
from typing import Any

from bench.auth.fixtures import FIVE_MINUTES_S, STARTUP_S, rings, services
from sdfr.testing.simnet import SimNet


def fleet_bytes(robots: int, n_services: int, seconds: float) -> dict[str, object]:
    """Per robot, bytes sent and received, open and keyed: during the start-up (the first
    STARTUP_S, everyone fetching everyone's set), then in `seconds` of steady state scaled to
    5 minutes.  Virtual time, so the numbers are exact and the run takes a second."""
    out: dict[str, Any] = {}
    for label, ring in rings():
        net = SimNet(seed=7)
        names = [f"r{i}" for i in range(1, robots + 1)]
        for name in names:
            net.add(name, services=services(name, n_services), keyring=ring)
        net.run_for(STARTUP_S)
        assert net.all_see_all(names)
        cores = [net.nodes[n].core for n in names]
        start = [(c.counters.bytes_out, c.counters.bytes_in) for c in cores]
        net.run_for(seconds)
        assert net.all_see_all(names)
        scale = FIVE_MINUTES_S / seconds
        out[label] = {
            "startup_tx_kb_per_robot": round(statistics.mean(s[0] for s in start) / 1000, 1),
            "startup_rx_kb_per_robot": round(statistics.mean(s[1] for s in start) / 1000, 1),
            "tx_kb_per_robot_5min": round(
                statistics.mean(
                    (c.counters.bytes_out - s[0]) * scale / 1000
                    for c, s in zip(cores, start, strict=True)
                ),
                1,
            ),
            "rx_kb_per_robot_5min": round(
                statistics.mean(
                    (c.counters.bytes_in - s[1]) * scale / 1000
                    for c, s in zip(cores, start, strict=True)
                ),
                1,
            ),
        }
    open_, keyed = out["open"], out["keyed"]
    for key in ("tx_kb_per_robot_5min", "rx_kb_per_robot_5min"):
        out[key.split("_")[0] + "_overhead_pct"] = round(100 * (keyed[key] / open_[key] - 1), 1)
    out["conditions"] = (
        f"{robots} robots, {n_services} services each, no churn, the 10 s beacon; steady state "
        f"over {seconds:.0f} s of virtual time after a {STARTUP_S:.0f} s start-up, scaled to 5 "
        "minutes (protocol core on an in-memory medium, no loss); UDP payload"
    )
    return out
