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
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from netlab import analysis
from netlab.analysis import Record

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from netlab.report import AgreementSample, ConnectivitySample

__all__ = [
    "Timeline",
    "agreement",
    "bytes_per_robot",
    "connectivity",
    "datagrams_per_type",
    "save",
]

_MAX_BINS = 60
_STEPS = (0.5, 1.0, 2.0, 5.0, 10.0, 15.0, 30.0, 60.0, 120.0, 300.0, 600.0)
_DPI = 110
_TIME_AXIS = "time since start of run (s); dotted: events, ▲: check deadlines"


#: Steps marked on every time axis, and how.
_MARKED = {
    "partition": ("partition", "#d62728"),
    "merge": ("merge", "#2ca02c"),
    "kill": ("kill -9", "#000000"),
    "stop": ("stop", "#7f7f7f"),
    "restart": ("restart", "#9467bd"),
    "collision": ("collision", "#ff7f0e"),
}


@dataclass(frozen=True, slots=True)
class Timeline:
    """What every time plot of a run shares: its axis (0 to `duration` seconds), its marked
    events (partitions, merges, kills...) and check deadlines, and the title naming the
    scenario and the run."""

    duration: float
    title: str
    events: tuple[tuple[float, str, str], ...] = ()  # (seconds, label, colour)
    deadlines: tuple[tuple[float, str], ...] = ()  # (seconds, check)
    lag: float | None = None  # the agreement plot's lag, when the run had one
    target: float | None = None  # the agreement check's threshold, when the run had one

    @classmethod
    def of(cls, meta: Mapping[str, Any], start: float, end: float, run: str) -> Timeline:
        scenario = meta.get("scenario")
        title = f"{scenario} · run {run}" if scenario else f"run {run}"
        steps = [s for s in meta.get("steps", []) if isinstance(s, Mapping)]
        events = []
        for s in steps:
            mark = _MARKED.get(str(s.get("kind")))
            if mark is not None and s.get("start") is not None:
                events.append((float(s["start"]) - start, s.get("label") or mark[0], mark[1]))
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
        )

    def axis(self, ax: Axes, *, labels: bool = True) -> None:
        """The run's time axis on `ax`, with its events (named at the top when `labels`) and
        its checks' deadlines (short ticks at the bottom)."""
        ax.set_xlim(0, max(self.duration, 1e-9))
        # Marks past the run's end (a deadline the run did not wait for) are left out; none
        # takes part in the layout, so a mark never squeezes the plot.
        inside = [e for e in self.events if 0 <= e[0] <= self.duration]
        for t, label, colour in inside:
            ax.axvline(t, color=colour, linestyle=":", linewidth=1.2, alpha=0.9)
            if labels:
                ax.annotate(
                    label, (t, 1.0), xycoords=("data", "axes fraction"), xytext=(2, -2),
                    textcoords="offset points", rotation=90, va="top", ha="left", fontsize=7,
                    color=colour, annotation_clip=True,
                ).set_in_layout(False)  # fmt: skip
        for t, _check in self.deadlines:
            if 0 <= t <= self.duration:
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


def bytes_per_robot(traffic: Mapping[str, Any], duration: float) -> Figure:
    robots: dict[str, Any] = traffic["robots"]
    names = list(robots)
    n = len(names)
    fig = _figure(max(7.0, 1.0 + 0.45 * n), 4.8)
    ax = fig.add_subplot()
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
    if duration > 0:
        tx = [robots[r].get("per_5_min_kB", {}).get("tx_payload", 0.0) for r in names]
        rx = [robots[r].get("per_5_min_kB", {}).get("rx_payload", 0.0) for r in names]
        ptx, prx = analysis.PAPER_TX_KB_5MIN, analysis.PAPER_RX_KB_5MIN
        fig.supxlabel(
            f"UDP payload at this rate over 5 min: TX {min(tx):.0f}-{max(tx):.0f} kB, "
            f"RX {min(rx):.0f}-{max(rx):.0f} kB per robot\n"
            f"(the paper, 5 min with its default 10 s beacon: TX {ptx[0]}-{ptx[1]} kB, "
            f"RX {prx[0]}-{prx[1]} kB)",
            fontsize=8,
            color="#444444",
        )
    return fig


def _step_for(duration: float) -> float:
    for step in _STEPS:
        if duration / step <= _MAX_BINS:
            return step
    return _STEPS[-1]


def datagrams_per_type(
    recs: Sequence[Record], start: float, end: float, timeline: Timeline
) -> Figure:
    step = _step_for(end - start)
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
    ax.set_xlabel(_TIME_AXIS)
    unit = "per second" if step == 1.0 else f"per second (mean over {step:g} s bins)"
    ax.set_ylabel(f"datagrams {unit}")
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
    top.set_ylim(bottom=0, top=max(1, max(s.linked_pairs for s in conn)) * 1.15)
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
    bottom.set_xlabel(_TIME_AXIS)
    bottom.set_ylabel("robot")
    return fig


def agreement(agree: Sequence[AgreementSample], start: float, timeline: Timeline) -> Figure:
    fig = _figure(8.0, 4.5)
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
    if 0 < len(robots) <= 10:
        for robot in robots:
            ys = [100.0 * s.per_robot.get(robot, math.nan) for s in agree]
            ax.plot(
                ts, ys, linewidth=0.8, alpha=0.6, marker="." if len(ts) < 60 else "", label=robot
            )
    ax.plot(
        ts, values, color="black", linewidth=2.0, marker="." if len(ts) < 60 else "", label="fleet"
    )
    if timeline.target is not None:  # only a run with an agreement check has a target
        ax.axhline(
            100 * timeline.target,
            color="#d62728",
            linestyle="--",
            linewidth=1.0,
            label=f"{100 * timeline.target:.0f} % (the run's check)",
        )
    timeline.axis(ax)
    ax.set_xlabel(_TIME_AXIS)
    ax.set_ylabel("pairs in agreement (%)")
    low = min([*values, 100 * (timeline.target or 1.0)])
    ax.set_ylim(max(0.0, math.floor(low / 10) * 10 - 5), 101)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right", ncols=min(4, len(robots) + 2))
    return fig


def _empty(ax: Axes, text: str) -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, color="#666666")
    ax.set_xticks([])
    ax.set_yticks([])
