"""The PNG plots of a run's report (matplotlib, Agg, no pyplot state): each function draws one
figure from what `netlab.report.write_report` computed and returns it; `save` writes it.

* `bytes_per_robot`: kilobytes each robot sent (TX) and received (RX), as whole frames and
  as UDP payload;
* `datagrams_per_type`: datagrams per second sent on the air, per message type;
* `connectivity`: linked pairs on the medium and reachable peers per robot over time;
* `agreement`: how far neighbour tables agree with the medium's true connectivity over time.
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from netlab import analysis
from netlab.paper import PAPER_CONDITIONS, PAPER_RX_KB_5MIN, PAPER_TX_KB_5MIN, RunConditions
from netlab.pcap import Record
from netlab.samples import AgreementSample, ConnectivitySample

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = [
    "Timeline",
    "agreement",
    "bin_width",
    "bytes_per_robot",
    "connectivity",
    "datagrams_per_type",
    "save",
]

#: Bins of a time series: the smallest width giving at most this many bins.
_MAX_BINS = 60
#: Widths tried when the run's beacon period is not known.
_STEPS = (0.5, 1.0, 2.0, 5.0, 10.0, 15.0, 30.0, 60.0, 120.0, 300.0, 600.0)
_DPI = 110
_TIME = "time since start of run (s)"

#: Steps marked on every time axis (a dotted line), and how.
_MARKED = {
    "start": ("start", "#1f77b4"),  # not the run's first start: a robot joining later
    "partition": ("partition", "#d62728"),
    "merge": ("merge", "#2ca02c"),
    "kill": ("kill -9", "#000000"),
    "stop": ("stop", "#7f7f7f"),
    "restart": ("restart", "#9467bd"),
    "collision": ("collision", "#ff7f0e"),
    "move": ("move", "#17becf"),
    "quality": ("link quality", "#bcbd22"),
    "shape": ("shaping", "#bcbd22"),
}
#: Steps that last (robots walking): shaded over their span, a dotted line where they begin.
_SPANS = {"mobility": ("mobility", "#17becf")}


@dataclass(frozen=True, slots=True)
class Timeline:
    """What every time plot of a run shares: its axis (0 to `duration` seconds), its marked
    events (partitions, merges, kills...), spans (robots walking) and check deadlines, and the
    title naming the scenario and the run."""

    duration: float
    title: str
    events: tuple[tuple[float, str, str], ...] = ()  # (seconds, label, colour)
    deadlines: tuple[tuple[float, str], ...] = ()  # (seconds, check)
    lag: float | None = None  # the agreement plot's lag, when the run had one
    target: float | None = None  # the agreement check's threshold, when the run had one
    spans: tuple[tuple[float, float, str, str], ...] = ()  # (from, to, label, colour)

    @classmethod
    def of(cls, meta: Mapping[str, Any], start: float, end: float, run: str) -> Timeline:
        scenario = meta.get("scenario")
        title = f"{scenario} · run {run}" if scenario else f"run {run}"
        steps = [s for s in meta.get("steps", []) if isinstance(s, Mapping)]
        events, spans = [], []
        started = False
        for s in steps:
            kind = str(s.get("kind"))
            if s.get("start") is None:
                continue
            begin = float(s["start"]) - start
            if kind in _SPANS and s.get("end") is not None:
                name, colour = _SPANS[kind]
                spans.append((begin, float(s["end"]) - start, s.get("label") or name, colour))
            elif kind in _MARKED and (kind != "start" or started):
                name, colour = _MARKED[kind]
                events.append((begin, s.get("label") or name, colour))
            started = started or kind == "start"
        # A check's deadline counts from the end of the last action step before it.
        deadlines = []
        checks = {c.get("step"): c for c in meta.get("checks", []) if isinstance(c, Mapping)}
        clock = None
        for s in steps:
            if s.get("kind") not in ("check", "wait"):
                clock = s.get("end")
                continue
            check = checks.get(s.get("step"))
            if check is not None and check.get("deadline_s") is not None and clock is not None:
                when = float(clock) + float(check["deadline_s"]) - start
                deadlines.append((when, str(check.get("description") or s.get("label") or "")))
        lag, target = meta.get("agreement_lag_s"), meta.get("agreement_target")
        return cls(
            end - start,
            title,
            tuple(events),
            tuple(deadlines),
            float(lag) if lag is not None else None,
            float(target) if target is not None else None,
            tuple(spans),
        )

    def _inside(self, t: float) -> bool:
        # Marks past the run's end (a deadline the run did not wait for) are left out.
        return 0 <= t <= self.duration

    def caption(self) -> str:
        """The time axis's label: what the marks drawn on it mean, and only those drawn."""
        parts = [_TIME]
        spans = [label for t, _end, label, _c in self.spans if self._inside(t)]
        if spans or any(self._inside(t) for t, _l, _c in self.events):
            parts.append("dotted: events")
        if spans:
            parts.append(f"shaded: {', '.join(dict.fromkeys(spans))}")
        if any(self._inside(t) for t, _check in self.deadlines):
            parts.append("▲: check deadlines")
        return "; ".join(parts)

    def axis(self, ax: Axes, *, labels: bool = True) -> None:
        """The run's time axis on `ax`, with its events and spans (named at the top when
        `labels`) and its checks' deadlines (short ticks at the bottom)."""
        ax.set_xlim(0, max(self.duration, 1e-9))
        lines = [(t, label, colour) for t, label, colour in self.events if self._inside(t)]
        for t, stop, label, colour in self.spans:
            if self._inside(t):
                ax.axvspan(t, min(stop, self.duration), color=colour, alpha=0.08, linewidth=0)
                lines.append((t, label, colour))
        # No mark takes part in the layout, so a mark never squeezes the plot.
        for t, label, colour in sorted(lines):
            ax.axvline(t, color=colour, linestyle=":", linewidth=1.2, alpha=0.9)
            if labels:
                ax.annotate(
                    label, (t, 1.0), xycoords=("data", "axes fraction"), xytext=(2, -2),
                    textcoords="offset points", rotation=90, va="top", ha="left", fontsize=7,
                    color=colour, annotation_clip=True,
                ).set_in_layout(False)  # fmt: skip
        for t, _check in self.deadlines:
            if self._inside(t):
                (tick,) = ax.plot(
                    [t], [0.0], marker="^", markersize=6, color="#d62728", clip_on=False,
                    transform=ax.get_xaxis_transform(), linestyle="none",
                )  # fmt: skip
                tick.set_in_layout(False)


def _figure(width: float = 8.0, height: float = 4.5) -> Figure:
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=_DPI, layout="constrained")


def save(fig: Figure, path: Path, timeline: Timeline) -> str:
    fig.suptitle(timeline.title, fontsize=9, color="#444444")
    fig.savefig(path, format="png")
    return path.name


def bytes_per_robot(traffic: Mapping[str, Any], conditions: RunConditions) -> Figure:
    """Bars of each robot's TX and RX kilobytes; below them the run's conditions, and the
    paper's figure 6 only when `conditions` are the paper's."""
    robots: dict[str, Any] = traffic["robots"]
    names = list(robots)
    n = len(names)
    fig = _figure(max(7.0, 1.0 + 0.45 * n), 4.8)
    ax = fig.add_subplot()
    duration = conditions.duration_s
    title = f"SDfR traffic per robot over {duration:.1f} s ({n} robot{'s' if n != 1 else ''})"
    ax.set_title(title)
    if not names:
        _empty(ax, "no SDfR datagrams captured")
        return fig
    xs = list(range(n))
    width = 0.38
    series = (
        ("tx", -width / 2, "#1f77b4", "#aec7e8", "TX"),
        ("rx", +width / 2, "#d62728", "#ff9896", "RX"),
    )
    for key, offset, dark, light, label in series:
        frame = [robots[r][f"{key}_kB"]["frame"] for r in names]
        payload = [robots[r][f"{key}_kB"]["payload"] for r in names]
        pos = [x + offset for x in xs]
        bars = ax.bar(pos, frame, width, color=light, label=f"{label}, whole Ethernet frames")
        ax.bar(pos, payload, width * 0.6, color=dark, label=f"{label}, UDP payload")
        if n <= 12:
            ax.bar_label(bars, fmt="%.1f", padding=2, fontsize=8)
    ax.set_xticks(xs, names, rotation=90 if n > 12 else 0)
    ax.set_xlabel("robot")
    ax.set_ylabel("kilobytes (1 kB = 1000 bytes)")
    top = max(robots[r][f"{d}_kB"]["frame"] for r in names for d in ("tx", "rx"))
    ax.set_ylim(0, top * 1.35 or 1.0)  # room above the bars for the legend
    ax.grid(axis="y", alpha=0.3)
    ax.legend(loc="upper left", fontsize=8, ncols=2)

    def payloads(key: str) -> list[float]:
        return [float(robots[r][key]["payload"]) for r in names]

    lines = [
        f"This run: {conditions.describe()}",
        f"UDP payload per robot: TX {_span(payloads('tx_kB'), '.1f')} kB, "
        f"RX {_span(payloads('rx_kB'), '.1f')} kB",
    ]
    differences = conditions.paper_differences()
    if differences:
        lines.append(
            f"Not set beside the paper's figure 6 ({PAPER_CONDITIONS}): "
            f"this run had {'; '.join(differences)}"
        )
    else:
        tx = [float(robots[r]["per_5_min_kB"]["tx_payload"]) for r in names]
        rx = [float(robots[r]["per_5_min_kB"]["rx_payload"]) for r in names]
        ptx, prx = PAPER_TX_KB_5MIN, PAPER_RX_KB_5MIN
        lines.append(
            f"Over 5 min at this rate: TX {_span(tx, '.0f')} kB, RX {_span(rx, '.0f')} kB; "
            f"the paper's figure 6 under the same conditions: "
            f"TX {ptx[0]}-{ptx[1]} kB, RX {prx[0]}-{prx[1]} kB per robot"
        )
    # Wrapped to the figure's width (about 15 characters an inch at this size).
    wrap = int(fig.get_figwidth() * 15)
    text = "\n".join(textwrap.fill(line, wrap, break_on_hyphens=False) for line in lines)
    fig.supxlabel(text, fontsize=8, color="#444444")
    return fig


def _span(values: Sequence[float], fmt: str) -> str:
    """'low-high' as printed, or one value when both print the same."""
    low, high = format(min(values), fmt), format(max(values), fmt)
    return low if low == high else f"{low}-{high}"


def bin_width(duration: float, beacon: float | None) -> float:
    """The width of a time series' bins: a whole number of beacon periods (1, 2, 5, 10, 20...),
    so that every bin holds as many beacons as the next; the smallest giving at most
    `_MAX_BINS` bins.  Without a beacon period, the smallest of `_STEPS` that does."""
    if beacon is None:
        return next((w for w in _STEPS if duration / w <= _MAX_BINS), _STEPS[-1])
    scale = 1
    while True:
        for k in (1, 2, 5):
            width = k * scale * beacon
            if duration / width <= _MAX_BINS:
                return width
        scale *= 10


def datagrams_per_type(
    recs: Sequence[Record],
    start: float,
    end: float,
    timeline: Timeline,
    *,
    beacon: float | None,
) -> Figure:
    """Datagrams per second sent on the air, stacked by message type, in bins of whole beacon
    periods (`bin_width`)."""
    step = bin_width(end - start, beacon)
    series = analysis.per_second(recs, by="type", step=step, start=start, end=end)
    fig = _figure(8.0, 4.5)
    ax = fig.add_subplot()
    ax.set_title("SDfR datagrams sent on the air, per message type")
    if not series.values:
        _empty(ax, "no SDfR datagrams captured")
        return fig
    lefts = series.times
    # The last bin ends with the run: a rate over its real width, not a full step.
    widths = [step] * series.bins
    widths[-1] = min(step, max(end - start - lefts[-1], step / 100))
    bottom = [0.0] * series.bins
    order = sorted(series.values, key=lambda k: -sum(series.values[k]))
    colors = _type_colors()
    for key in order:
        rates = [v / w for v, w in zip(series.values[key], widths, strict=True)]
        total = int(sum(series.values[key]))
        ax.bar(
            lefts,
            rates,
            width=widths,
            bottom=bottom,
            align="edge",
            color=colors.get(key),
            edgecolor="white" if series.bins <= 60 else "none",
            linewidth=0.5,
            label=f"{key} ({total})",
        )
        bottom = [b + r for b, r in zip(bottom, rates, strict=True)]
    ax.set_xlabel(timeline.caption())
    ax.set_ylabel(f"datagrams/s, bins of {step:g} s{_in_beacons(step, beacon)}")
    timeline.axis(ax)
    ax.set_ylim(0, max(bottom) * 1.15 or 1.0)
    ax.grid(axis="y", alpha=0.3)
    ax.set_axisbelow(True)
    ax.legend(
        title="type (datagrams in all)",
        fontsize=8,
        title_fontsize=8,
        loc="upper left",
        bbox_to_anchor=(1.01, 1.0),
    )
    return fig


def _in_beacons(step: float, beacon: float | None) -> str:
    if beacon is None:
        return " (beacon unknown)"
    k = round(step / beacon)
    return f" ({k} beacon{'s' if k != 1 else ''})"


def _type_colors() -> dict[str, str]:
    """One fixed colour per message type, the same in every report."""
    return {
        "Alive": "#1f77b4",
        "Update": "#ff7f0e",
        "Discovery": "#2ca02c",
        "Response": "#98df8a",
        "Ping": "#9467bd",
        "Ping reply": "#c5b0d5",
        "Byebye": "#8c564b",
        "Reject": "#d62728",
    }


def connectivity(
    conn: Sequence[ConnectivitySample], start: float, end: float, timeline: Timeline
) -> Figure:
    from matplotlib.ticker import MaxNLocator

    fig = _figure(8.0, 6.0)
    top, bottom = fig.subplots(2, 1, sharex=True)
    # A sample holds until the next one; the last until the end of the run (or one interval).
    ts = [s.time - start for s in conn]
    gap = (ts[-1] - ts[-2]) if len(ts) > 1 else 1.0
    edges = [*ts, end - start if end - start > ts[-1] else ts[-1] + gap]
    top.set_title("Connectivity over time")
    top.stairs([s.linked_pairs for s in conn], edges, baseline=None, label="linked pairs (medium)")
    if any(s.reachable_pairs is not None for s in conn):
        pairs = [math.nan if s.reachable_pairs is None else s.reachable_pairs for s in conn]
        top.stairs(pairs, edges, baseline=None, linestyle="--", label="pairs listing each other")
    timeline.axis(top)
    top.set_ylabel("robot pairs")
    # Both lines fit: more pairs can list each other than the medium links (stale entries).
    pairs_max = max(max(s.linked_pairs, s.reachable_pairs or 0) for s in conn)
    top.set_ylim(bottom=0, top=max(1, pairs_max) * 1.15)
    top.yaxis.set_major_locator(MaxNLocator(integer=True))
    top.grid(alpha=0.3)
    top.legend(fontsize=8, loc="best")

    robots = analysis.natural_order(sorted({r for s in conn for r in s.reachable}))
    bottom.set_title("Peers each robot lists as reachable", fontsize=10)
    if robots:
        # One row per robot, coloured by its count: no lines hiding each other, and it scales
        # to a 50-robot lab.
        grid = [[s.reachable.get(robot, math.nan) for s in conn] for robot in robots]
        most = max(1, max((v for row in grid for v in row if v == v), default=1))
        mesh = bottom.pcolormesh(
            edges,
            range(len(robots) + 1),
            grid,
            cmap="viridis",
            vmin=0,
            vmax=most,
            shading="flat",
        )
        # Spanning both panels keeps their time axes aligned; drawn level with the bottom one.
        bar = fig.colorbar(mesh, ax=[top, bottom], pad=0.01, shrink=0.48, anchor=(0.0, 0.0))
        bar.set_label("reachable peers")
        bar.ax.yaxis.set_major_locator(MaxNLocator(integer=True))
        bottom.set_yticks([i + 0.5 for i in range(len(robots))], robots)
        bottom.invert_yaxis()
        if len(robots) > 20:
            bottom.tick_params(axis="y", labelsize=6)
    else:
        _empty(bottom, "no per-robot samples")
    timeline.axis(bottom, labels=False)
    bottom.set_xlabel(timeline.caption())
    bottom.set_ylabel("robot")
    return fig


#: Up to this many robots get a line of their own in the agreement plot.
_MAX_ROBOT_LINES = 10
#: Per robot: a colour (tab10), a marker and a line style, so that no two lines look alike
#: even where they overlap or in grey.  No dotted style: dotted lines are the run's events.
_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*", "<", ">")
_LINESTYLES = ("-", "--", "-.")


def agreement(agree: Sequence[AgreementSample], start: float, timeline: Timeline) -> Figure:
    """The fleet's agreement over time (black), each robot's (up to `_MAX_ROBOT_LINES`), and
    the run's check threshold; the y axis runs from the lowest value drawn to 100 %."""
    fig = _figure(8.8, 4.5)
    ax = fig.add_subplot()
    ts = [s.time - start for s in agree]
    values = [100.0 * s.agreement for s in agree]
    mean = sum(values) / len(values)
    lag = f", lists allowed {timeline.lag:g} s to follow" if timeline.lag is not None else ""
    ax.set_title(
        f"Neighbour lists vs. the medium's links (mean agreement {mean:.1f} %{lag})",
        fontsize=10,
    )
    robots = analysis.natural_order(sorted({r for s in agree for r in s.per_robot}))
    drawn = list(values)
    if len(robots) <= _MAX_ROBOT_LINES:
        every = max(1, len(ts) // 15)  # markers spaced out, each robot's a little shifted
        for i, robot in enumerate(robots):
            ys = [100.0 * s.per_robot.get(robot, math.nan) for s in agree]
            drawn += [y for y in ys if not math.isnan(y)]
            ax.plot(
                ts, ys, color=f"C{i}", linestyle=_LINESTYLES[i % len(_LINESTYLES)],
                marker=_MARKERS[i], markevery=(i % every, every), markersize=4, linewidth=1.3,
                label=robot,
            )  # fmt: skip
    else:
        ax.plot([], [], linestyle="none", label=f"{len(robots)} robots: each one's in report.json")
    ax.plot(ts, values, color="black", linewidth=2.2, label="fleet", zorder=3)
    if timeline.target is not None:  # only a run with an agreement check has a target
        ax.axhline(
            100 * timeline.target,
            color="#d62728",
            linestyle="--",
            linewidth=1.0,
            label=f"{100 * timeline.target:.0f} % (the run's check)",
        )
        drawn.append(100 * timeline.target)
    timeline.axis(ax)
    ax.set_xlabel(timeline.caption())
    ax.set_ylabel("pairs in agreement (%)")
    # From the lowest value drawn, rounded down to ten (at least 10 points of range), to 100.
    low = min(90.0, max(0.0, math.floor(min(drawn) / 10) * 10))
    pad = 0.03 * (100 - low)
    ax.set_ylim(low - pad, 100 + pad)
    ax.grid(alpha=0.3)
    # Beside the axes, never over a line.
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return fig


def _empty(ax: Axes, text: str) -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, color="#666666")
    ax.set_xticks([])
    ax.set_yticks([])
