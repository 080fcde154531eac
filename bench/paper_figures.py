"""The paper's figures 4-6 drawn again from a `bench.paper` result, the paper's numbers beside
ours: `figures(result)` is the data of every figure (JSON), `write(figures, folder)` writes
``figures.json`` and the PNGs (matplotlib, Agg, no pyplot state)."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bench.paper_measure import PAPER, PAPER_MEMORY_MIB, dig

if TYPE_CHECKING:
    from matplotlib.axes import Axes

_DPI = 110
OURS = "#1f77b4"
OURS_P99 = "#aec7e8"
PAPER_COLOR = "#ff7f0e"


def figures(result: dict[str, Any]) -> dict[str, Any]:
    """The data of figures 4, 5 and 6 (and the bytes per robot as the fleet grows)."""
    runs = result.get("runs", [])
    names = [r["config"] for r in runs]
    fig4 = {
        "title": "Request time under the paper's load (paper: figure 4)",
        "unit": "ms",
        "runs": names,
        "ours": {
            "publish_p50": [dig(r, "latency", "publish", "p50_ms") for r in runs],
            "publish_p99": [dig(r, "latency", "publish", "p99_ms") for r in runs],
            "unpublish_p50": [dig(r, "latency", "unpublish", "p50_ms") for r in runs],
            "unpublish_p99": [dig(r, "latency", "unpublish", "p99_ms") for r in runs],
            "neighbors_p50": [dig(r, "latency", "neighbors", "p50_ms", "mean") for r in runs],
            "neighbors_p99": [dig(r, "latency", "neighbors", "p99_ms", "max") for r in runs],
        },
        "paper": {
            "publish_ms": list(PAPER["publish_ms"]),  # type: ignore[call-overload]
            "unpublish_ms": list(PAPER["unpublish_ms"]),  # type: ignore[call-overload]
            "neighbors_ms_max": PAPER["neighbors_ms_max"],
            "note": "the paper gives ranges over all its runs (average request times)",
        },
    }
    fig5 = {
        "title": "CPU and memory of the daemon under the paper's load (paper: figure 5)",
        "runs": names,
        "ours": {
            "cpu_percent_mean": [dig(r, "resources", "cpu_percent", "mean") for r in runs],
            "cpu_percent_max": [dig(r, "resources", "cpu_percent", "max") for r in runs],
            "discovery_cpu_percent_mean": [
                dig(r, "resources", "discovery_cpu_percent", "mean") for r in runs
            ],
            "pss_mib_mean": [dig(r, "resources", "pss_mib", "mean") for r in runs],
            "pss_mib_max": [dig(r, "resources", "pss_mib", "max") for r in runs],
        },
        "paper": {
            "cpu_percent": list(PAPER["cpu_percent"]),  # type: ignore[call-overload]
            "memory_mib_max": round(PAPER_MEMORY_MIB, 1),
            "note": "memory: under 0.3 % of 4 GB; CPU of a Core 2 Duo, 2.1 GHz",
        },
    }
    fig6 = {
        "title": "Bytes per robot in 5 minutes under the paper's load (paper: figure 6)",
        "unit": "kB (1000 B) per robot per 5 min",
        "runs": names,
        "ours": {
            key: [dig(r, "traffic", "per_5_min_kB", key, "mean") for r in runs]
            for key in ("tx_payload", "rx_payload", "tx_frame", "rx_frame")
        },
        "ours_max": {
            key: [dig(r, "traffic", "per_5_min_kB", key, "max") for r in runs]
            for key in ("tx_payload", "rx_payload")
        },
        "paper": {
            "tx_kB": list(PAPER["tx_kB_5min"]),  # type: ignore[call-overload]
            "rx_kB": list(PAPER["rx_kB_5min"]),  # type: ignore[call-overload]
        },
    }
    scale = result.get("scale", [])
    growth = {
        "title": "Bytes per robot in 5 minutes as the fleet grows (70 % publishers, no consumers)",
        "robots": [r["robots"] for r in scale],
        "ours": {
            key: [dig(r, "traffic", "per_5_min_kB", key, "mean") for r in scale]
            for key in ("tx_payload", "rx_payload", "tx_frame", "rx_frame")
        },
    }
    out = {"fig4": fig4, "fig5": fig5, "fig6": fig6, "growth": growth}
    if "side_by_side" in result:
        out["side_by_side"] = result["side_by_side"].get("table")
    return out


def write(figs: dict[str, Any], folder: Path) -> dict[str, str]:
    """figures.json and the PNGs in `folder`; their paths."""
    paths = {"json": str(folder / "figures.json")}
    (folder / "figures.json").write_text(json.dumps(figs, indent=2) + "\n")
    if figs["fig4"]["runs"]:
        paths["fig4"] = _save(_fig4(figs["fig4"]), folder / "fig4-latency.png")
        paths["fig5"] = _save(_fig5(figs["fig5"]), folder / "fig5-cpu-memory.png")
        paths["fig6"] = _save(_fig6(figs["fig6"]), folder / "fig6-traffic.png")
    if figs["growth"]["robots"]:
        paths["growth"] = _save(_growth(figs["growth"]), folder / "growth-traffic.png")
    return paths


def _save(fig: Any, path: Path) -> str:
    fig.savefig(path)
    return str(path)


def _figure(width: float, height: float) -> Any:
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=_DPI, layout="constrained")


def _num(values: Sequence[Any]) -> list[float]:
    return [float(v) if v is not None else 0.0 for v in values]


def _bars(ax: Axes, runs: Sequence[str], p50: Sequence[Any], p99: Sequence[Any] | None) -> None:
    x = list(range(len(runs)))
    if p99 is not None:
        ax.bar(x, _num(p99), width=0.6, color=OURS_P99, label="ours p99")
    ax.bar(x, _num(p50), width=0.6, color=OURS, label="ours p50" if p99 is not None else "ours")
    ax.set_xticks(x, [r.replace("static-", "s").replace("dynamic-", "d") for r in runs])
    ax.tick_params(axis="x", labelrotation=45, labelsize=8)


def _band(ax: Axes, lo: float, hi: float, label: str) -> None:
    ax.axhspan(lo, hi, color=PAPER_COLOR, alpha=0.3, label=label)


def _fig4(f: dict[str, Any]) -> Any:
    fig = _figure(12, 4)
    axes = fig.subplots(1, 3)
    o, p = f["ours"], f["paper"]
    for ax, op, title in zip(axes, ("publish", "unpublish", "neighbors"), ("publish",
                             "unpublish", "neighbour list"), strict=True):  # fmt: skip
        _bars(ax, f["runs"], o[f"{op}_p50"], o[f"{op}_p99"])
        if op == "neighbors":
            ax.axhline(p["neighbors_ms_max"], color=PAPER_COLOR, lw=2, label="paper (< 5 ms)")
        else:
            lo, hi = p[f"{op}_ms"]
            _band(ax, lo, hi, f"paper {lo:g}-{hi:g} ms")
        ax.set_title(title)
        ax.set_ylabel("ms")
        ax.set_yscale("log")
        ax.set_ylim(bottom=0.1)
        ax.legend(fontsize=7)
    fig.suptitle(f["title"] + " (s = static, d = dynamic; robots-publishers %)")
    return fig


def _fig5(f: dict[str, Any]) -> Any:
    fig = _figure(10, 4)
    cpu_ax, mem_ax = fig.subplots(1, 2)
    o, p = f["ours"], f["paper"]
    _bars(cpu_ax, f["runs"], o["cpu_percent_mean"], None)
    cpu_ax.plot(
        range(len(f["runs"])), _num(o["discovery_cpu_percent_mean"]), "k_", ms=14,
        label="discovery layer alone",
    )  # fmt: skip
    lo, hi = p["cpu_percent"]
    _band(cpu_ax, lo, hi, f"paper {lo}-{hi} %")
    cpu_ax.set_title("CPU, % of one core (whole daemon, mean over robots)")
    cpu_ax.legend(fontsize=7)
    _bars(mem_ax, f["runs"], o["pss_mib_mean"], None)
    mem_ax.axhline(p["memory_mib_max"], color=PAPER_COLOR, lw=2, label="paper (< 0.3 % of 4 GB)")
    mem_ax.set_title("memory: PSS of the daemon's processes, MiB")
    mem_ax.legend(fontsize=7)
    fig.suptitle(f["title"])
    return fig


def _fig6(f: dict[str, Any]) -> Any:
    fig = _figure(10, 4)
    tx_ax, rx_ax = fig.subplots(1, 2)
    o, p = f["ours"], f["paper"]
    for ax, d in ((tx_ax, "tx"), (rx_ax, "rx")):
        _bars(ax, f["runs"], o[f"{d}_payload"], o[f"{d}_frame"])
        lo, hi = p[f"{d}_kB"]
        _band(ax, lo, hi, f"paper {lo:g}-{hi:g} kB")
        ax.set_title(f"{d.upper()} kB per robot in 5 min (dark: UDP payload, light: frames)")
        ax.legend(fontsize=7)
    fig.suptitle(f["title"])
    return fig


def _growth(f: dict[str, Any]) -> Any:
    fig = _figure(6, 4)
    ax = fig.subplots()
    for key, style in (("tx_payload", "o-"), ("rx_payload", "s-")):
        ax.plot(f["robots"], _num(f["ours"][key]), style, label=key.replace("_", " "))
    ax.set_xlabel("robots")
    ax.set_ylabel("kB per robot in 5 min")
    ax.set_xticks(f["robots"])
    ax.legend()
    ax.set_title(f["title"], fontsize=9)
    return fig
