"""The paper's figures 4-6 drawn again from a `bench.paper` result, the paper's numbers beside
ours: `figures(result)` is the data of every figure (JSON), `write(figures, folder)` writes
``figures.json`` and the PNGs (matplotlib, Agg, no pyplot state)."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bench import peers_report
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


def _bars(
    ax: Axes,
    runs: Sequence[str],
    front: Sequence[Any],
    back: Sequence[Any] | None,
    labels: tuple[str, str] = ("ours p50", "ours p99"),
) -> None:
    """Our bars: `front` (dark) before `back` (light, taller: a p99 behind its p50, frames
    behind their payload)."""
    x = list(range(len(runs)))
    if back is not None:
        ax.bar(x, _num(back), width=0.6, color=OURS_P99, label=labels[1])
    ax.bar(x, _num(front), width=0.6, color=OURS, label=labels[0] if back is not None else "ours")
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
        _bars(ax, f["runs"], o[f"{d}_payload"], o[f"{d}_frame"], ("UDP payload", "whole frames"))
        lo, hi = p[f"{d}_kB"]
        _band(ax, lo, hi, f"paper {lo:g}-{hi:g} kB")
        ax.set_title(f"{d.upper()} kB per robot in 5 min", fontsize=10)
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


def _n(v: Any, fmt: str = ".1f") -> str:
    return "—" if not isinstance(v, int | float) or v != v else format(v, fmt)


def _pair(a: Any, b: Any, fmt: str = ".1f") -> str:
    return f"{_n(a, fmt)} / {_n(b, fmt)}"


def markdown(result: dict[str, Any]) -> str:
    """The run's tables for the docs (Markdown): figures 4-6 per run with the paper's numbers,
    the side-by-side with python-zeroconf, and the bytes as the fleet grows."""
    minutes = result.get("minutes_per_run") or 5.0
    head = (
        f"`make bench-paper`, {result.get('mode', 'full')} run: {minutes:g} min of load per "
        f"run, 10 s beacon, {dig(result, 'machine', 'nproc')} cores; loads in bench-paper.json."
    )
    out = [head, ""]
    out += [
        "| run | publish p50 / p99 (ms) | unpublish p50 / p99 (ms) | neighbours p50 / p99 (ms) "
        "| neighbour lists answered /s per robot | CPU % of a core: daemon (discovery) | PSS "
        "MiB | TX kB / 5 min | RX kB / 5 min | changes seen by every peer within 0.5 s |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in result.get("runs", []):
        lat, res = r.get("latency", {}), r.get("resources", {})
        per_5 = dig(r, "traffic", "per_5_min_kB") or {}
        asked = dig(lat, "neighbors", "requests")
        rate = asked / (minutes * 60) / r["robots"] if isinstance(asked, int) else None
        seen = dig(r, "seen_by_peers", "within_bound") or {}
        out.append(
            f"| {r['config']} "
            f"| {_pair(dig(lat, 'publish', 'p50_ms'), dig(lat, 'publish', 'p99_ms'))} "
            f"| {_pair(dig(lat, 'unpublish', 'p50_ms'), dig(lat, 'unpublish', 'p99_ms'))} "
            f"| {_pair(dig(lat, 'neighbors', 'p50_ms', 'mean'), dig(lat, 'neighbors', 'p99_ms', 'max'))} "  # noqa: E501
            f"| {_n(rate, ',.0f')} "
            f"| {_n(dig(res, 'cpu_percent', 'mean'))} "
            f"({_n(dig(res, 'discovery_cpu_percent', 'mean'), '.2f')}) "
            f"| {_n(dig(res, 'pss_mib', 'mean'))} "
            f"| {_n(dig(per_5, 'tx_payload', 'mean'))} | {_n(dig(per_5, 'rx_payload', 'mean'))} "
            f"| {_pair(seen.get('publish'), seen.get('unpublish'), '.1%')} |"
        )  # fmt: skip
    p: dict[str, Any] = PAPER

    def span(key: str) -> str:
        lo, hi = p[key]
        return f"{lo:g}-{hi:g}"

    out.append(
        f"| the paper (its ranges over all runs) | {span('publish_ms')} | {span('unpublish_ms')} "
        f"| under {p['neighbors_ms_max']:g} | — | {span('cpu_percent')} "
        f"| under {PAPER_MEMORY_MIB:.0f} | {span('tx_kB_5min')} | {span('rx_kB_5min')} | — |"
    )
    if dig(result, "side_by_side", "table"):
        out += ["", *peers_report.markdown(result["side_by_side"])]
    scale = result.get("scale") or []
    if scale:
        out += [
            "",
            "Bytes per robot as the fleet grows (70 % publishers, no consumers), kB per 5 min:",
            "",
            "| robots | TX payload | RX payload | TX frames | RX frames |",
            "| --- | --- | --- | --- | --- |",
        ]
        for r in scale:
            per_5 = dig(r, "traffic", "per_5_min_kB") or {}
            cells = [
                _n(dig(per_5, k, "mean"))
                for k in ("tx_payload", "rx_payload", "tx_frame", "rx_frame")
            ]
            out.append(f"| {r['robots']} | {' | '.join(cells)} |")
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    """`python -m bench.paper_figures RESULT.json [--draw DIR]`: the run's tables (Markdown) on
    stdout, and its figures drawn again."""
    import argparse

    p = argparse.ArgumentParser(description=main.__doc__)
    p.add_argument("result", type=Path, help="a bench-paper.json")
    p.add_argument("--draw", type=Path, metavar="DIR", help="also draw its figures again in DIR")
    args = p.parse_args(argv)
    result = json.loads(args.result.read_text())
    if args.draw:
        args.draw.mkdir(parents=True, exist_ok=True)
        write(figures(result), args.draw)
    print(markdown(result), end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
