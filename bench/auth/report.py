"""The bench's figures as a table on stderr."""

from __future__ import annotations

import sys
from typing import Any

from bench.auth.dynamics import DELAYS, WHATS


def report(result: dict[str, Any]) -> None:
    err = sys.stderr
    print(f"\n{'datagram':34} {'unsigned':>9} {'signed':>7} {'+bytes':>7} {'+%':>6}", file=err)
    for kind, row in result["bytes_per_datagram"].items():
        print(
            f"{kind:34} {row['unsigned']:9.0f} {row['signed']:7.0f} {row['overhead']:7.0f} "
            f"{row['overhead_pct']:6.1f}",
            file=err,
        )
    print("\nCPU, µs per datagram (median):", file=err)
    for label, row in result["cpu_per_datagram"].items():
        print(
            f"  {label:18} seal {row['seal_us']:6.2f}  check {row['check_us']:6.2f}  "
            f"check of an unsigned one {row['check_unsigned_us']:5.2f}",
            file=err,
        )
    rp = result["receive_path"]
    print(
        f"  whole receive path: unsigned {rp['unsigned_us']:.1f}, signed {rp['signed_us']:.1f} "
        f"(+{rp['overhead_us']:.1f})",
        file=err,
    )
    fl = result["fleet"]
    print(f"\nFleet ({fl['conditions']}):", file=err)
    for label in ("open", "keyed"):
        row = fl[label]
        print(
            f"  {label:5} TX {row['tx_kb_per_robot_5min']:7.1f} kB  "
            f"RX {row['rx_kb_per_robot_5min']:7.1f} kB per robot per 5 min "
            f"(start-up: TX {row['startup_tx_kb_per_robot']:.1f}, "
            f"RX {row['startup_rx_kb_per_robot']:.1f} kB)",
            file=err,
        )
    print(
        f"  keyed: TX {fl['tx_overhead_pct']:+.1f} %, RX {fl['rx_overhead_pct']:+.1f} %", file=err
    )
    dy = result["dynamics"]
    print("\nDynamics (s: median / max):", file=err)
    for label in ("open", "keyed"):
        side = dy[label]
        for dlabel in DELAYS:
            row = side[dlabel]
            cells = "  ".join(
                f"{what} {row[what]['median_s']} / {row[what]['max_s']}"
                for what in (*WHATS, "change_seen")
            )
            print(f"  {label:5} {dlabel:8} {cells}", file=err)
        print(f"  {label:5} link delays on the path: {side['link_delays_on_the_path']}", file=err)
        for what in ("idle", "churn"):
            row = side[what]
            print(
                f"  {label:5} {what:5} TX {row['tx_bytes_per_robot_min']:8.1f} B/min "
                f"({row['tx_datagrams_per_robot_min']:.1f} datagrams)  "
                f"RX {row['rx_bytes_per_robot_min']:8.1f} B/min per robot",
                file=err,
            )
    print(f"\nwall time {result['wall_s']} s; sdfr {result['core']}", file=err)
    if "side_by_side" in result:
        old = result["baseline"]["core"]
        print(f"\nSide by side: old = {old['git']} ({old['sdfr']}), new = this run", file=err)
        print(f"{'figure':96} {'old':>12} {'new':>12} {'change':>10}", file=err)
        for path, row in result["side_by_side"].items():
            a, b = row["old"], row["new"]
            ch = row.get("change_pct")
            print(
                f"{path[:96]:96} {fmt(a):>12} {fmt(b):>12} "
                f"{'' if ch is None else f'{ch:+.1f} %':>10}",
                file=err,
            )


def fmt(v: float | None) -> str:
    if v is None:
        return "-"
    return f"{v:.3f}".rstrip("0").rstrip(".") if isinstance(v, float) else str(v)
