"""What the side-by-side's results say, as pure functions: its table (a row per measure, a
column per system, each peer's ratio to SDfR), the table in Markdown, and the figure of bytes
per robot as the fleet grows, a line per system.  Nothing here starts anything."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from bench import change_path
from bench.paper_measure import dig


def _loss(r: dict[str, Any]) -> float:
    """The run's loss on every pair, in % (0: a clean medium)."""
    return float(dig(r, "timing_s", "loss") or 0.0)


def _fmt(v: Any, unit: str = " s") -> str:
    return "not seen" if v is None else f"{v:.2f}{unit}" if isinstance(v, float) else str(v)


def table(r: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per measure: each system's value (by its name: ``sdfr``, ``zeroconf``, ...)
    and each peer's ratio to SDfR (peer / SDfR)."""
    systems = list(r["systems"])
    peers = systems[1:]
    rows: list[dict[str, Any]] = []

    def row(measure: str, values: dict[str, Any], note: str = "") -> None:
        sdfr = values.get("sdfr")
        ratio = {
            s: round(values[s] / sdfr, 2)
            for s in peers
            if isinstance(sdfr, int | float) and isinstance(values.get(s), int | float) and sdfr
        }
        rows.append({"measure": measure, **{s: values.get(s) for s in systems},
                     "ratio": ratio, "note": note})  # fmt: skip

    def each(key: str, *path: str) -> dict[str, Any]:
        return {s: dig(r.get(key, {}), s, *path) for s in systems}

    def named(counts: dict[str, Any]) -> str:
        return ", ".join(f"{r['systems'][s]['label']} {counts.get(s, '?')}" for s in systems)

    row("start-up: all robots list all services (s)", each("startup_s"))
    row("a new service seen on all peers (s)", each("new_service_s"))
    stale = {s: len(v) for s, v in r.get("stale_after_leave", {}).items()}
    row("a graceful leave seen on all peers (s)", each("graceful_leave_s"),
        "its services at the leave; still listed after it, of those it had unpublished "
        f"before: {named(stale)}")  # fmt: skip
    tcp = [r["systems"][s]["label"] for s in peers if "tcp" in str(dig(r, "traffic", "flows", s))]
    row(f"a kill -9 seen on all peers (s, waited at most {r['kill_cap_s']:g} s)", each("kill_9_s"),
        "None: not seen within the cap"
        + (f"; {', '.join(tcp)}: the kernel closes a killed process's TCP sessions, so a kill -9 "
           "is no silent departure to it (the partition's rows are)" if tcp else ""))  # fmt: skip
    row(f"{r['partition_s']:g} s partition: each half stops listing the other (s)",
        each("partition", "halves_dropped_each_other_s"),
        "a silent departure to every system (no packet crosses); None: not within it")  # fmt: skip
    row("after the merge, every list right again (s)",
        each("partition", "all_lists_right_after_merge_s"),
        f"None: not within {r['timing_s']['after_merge']:g} s")  # fmt: skip
    traffic = r.get("traffic", {})
    for key, label, what in (
        ("tx_payload", "TX", "payload"),
        ("rx_payload", "RX", "payload"),
        ("tx_frame", "TX", "whole frames"),
        ("rx_frame", "RX", "whole frames"),
    ):
        row(f"{label} kB per robot per 5 min ({what}; mean of robots)",
            {s: dig(traffic, "per_5_min_kB", s, key, "mean") for s in systems})  # fmt: skip
    row("datagrams (TCP segments) sent per robot per second (mean)",
        {s: dig(traffic, "tx_datagrams_per_s", s, "mean") for s in systems},
        "; ".join(f"{r['systems'][s]['label']}: {', '.join(f)}"
                  for s, f in traffic.get("flows", {}).items()))  # fmt: skip
    row("CPU per robot, % of one core (mean)", each("resources", "cpu_percent", "mean"),
        "SDfR: the daemon's processes (its API streaming events to the watcher included); "
        "a peer: its node's process")  # fmt: skip
    row("PSS per robot, MiB (mean of the robots' max)", each("resources", "pss_mib", "mean"))
    seen = r.get("seen_by_peers", {})
    row("churn: a change listed by each peer, p50 / p99 (ms)",
        {s: f"{dig(seen, s, 'publish', 'p50_ms')} / {dig(seen, s, 'publish', 'p99_ms')}"
         for s in systems},
        "publishes, from the moment each was asked for")  # fmt: skip
    return rows


def markdown(r: dict[str, Any]) -> list[str]:
    """The table as Markdown, a column per system, then each peer's ratio to SDfR."""
    systems = r["systems"]
    peers = list(systems)[1:]
    head = [v["label"] for v in systems.values()]
    head += [f"{systems[p]['label']} ÷ SDfR" for p in peers]
    loss = _loss(r)
    medium = f"{loss:g} % loss on every pair" if loss else "a clean medium"
    out = [
        f"Side by side, one lab of {r.get('robots')} robots on {medium}, "
        f"{r.get('publishers_per_robot')} services each under the same churn, every system at "
        "once. Knobs: " + "; ".join(f"{v['label']}: {v['knob']}" for v in systems.values()) + ".",
        *floor_line(r),
        *change_path.sentence(r.get("sdfr_change_path") or {}),
        "",
        f"| measure | {' | '.join(head)} | note |",
        "|" + " --- |" * (len(head) + 2),
    ]
    for row in r["table"]:
        cells = [_fmt(row.get(s), "") for s in systems]
        cells += [_fmt(row["ratio"].get(p), "") if p in row["ratio"] else "—" for p in peers]
        out.append(f"| {row['measure']} | {' | '.join(cells)} | {row.get('note', '')} |")
    return out


def floor_line(r: dict[str, Any]) -> list[str]:
    """What no system can beat: a bare multicast datagram's one-way time on the medium."""
    parts = []
    for key, when in (("idle", "before the systems started"), ("under_load", "during the churn")):
        f = dig(r, "floor", "idle") if key == "idle" else r.get("floor_under_load")
        if f:
            parts.append(
                f"{when} p50 {_fmt(f.get('p50_ms'), ' ms')}, p99 {_fmt(f.get('p99_ms'), ' ms')} "
                f"({f.get('arrived')} of {f.get('sent')} arrived)"
            )
    if not parts:
        return []
    return [f"The floor, a bare multicast datagram {dig(r, 'floor', 'idle', 'from') or 'r1'} to "
            f"{dig(r, 'floor', 'idle', 'to') or 'r2'}: " + "; ".join(parts) + "."]  # fmt: skip


def growth_figure(results: list[dict[str, Any]], path: Path) -> Path:
    """Bytes per robot per 5 minutes (whole frames sent and received) against the fleet's
    size, a line per system (and per loss, dashed when lossy)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7.5, 4.2), dpi=120, layout="constrained")
    axes = fig.subplots(1, 2, sharex=True)
    runs = sorted(results, key=lambda r: (_loss(r), r["robots"]))
    for ax, key, title in ((axes[0], "tx_frame", "sent"), (axes[1], "rx_frame", "received")):
        for loss in sorted({_loss(r) for r in runs}):
            these = [r for r in runs if _loss(r) == loss]
            for system, info in these[0]["systems"].items():
                ys = [dig(r, "traffic", "per_5_min_kB", system, key, "mean") for r in these]
                xs = [r["robots"] for r, y in zip(these, ys, strict=True) if y is not None]
                label = info["label"] + (f", {loss:g} % loss" if loss else "")
                ax.plot(xs, [y for y in ys if y is not None], marker="o",
                        linestyle="--" if loss else "-", label=label)  # fmt: skip
        ax.set_yscale("log")
        ax.set_xlabel("robots in the fleet")
        ax.set_ylabel(f"kB {title} per robot per 5 min (frames)")
        ax.set_title(f"bytes {title}")
        ax.grid(True, which="both", alpha=0.3)
    axes[1].legend(fontsize="small")
    fig.savefig(path)
    return path
