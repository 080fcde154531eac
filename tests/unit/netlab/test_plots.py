"""The report's plots do not mislead (issue 26): their axes show all the data, their lines can be
told apart, their captions say what is drawn, the per-type bins are whole beacons, and a run's
traffic is set beside the paper's only when it was measured under the paper's conditions.

Synthetic samples and records; the assertions read the matplotlib figures' axes and texts."""

from __future__ import annotations

import json
import random
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("matplotlib")

from matplotlib.lines import Line2D
from matplotlib.patches import Rectangle

from netlab import plots
from netlab.pcap import Record
from netlab.report import write_report
from netlab.samples import AgreementSample, ConnectivitySample

T0 = 1_800_000_000.0
ROBOTS = [f"r{i}" for i in range(1, 7)]


def agreement_samples(dip: float = 0.0) -> list[AgreementSample]:
    """Six robots agreeing fully, but r2 falls to `dip` (and the fleet to 80 %) for 3 s."""
    out = []
    for k in range(40):
        t = k * 0.25
        low = 3.0 <= t < 6.0
        per = {r: (dip if low and r == "r2" else 1.0) for r in ROBOTS}
        out.append(AgreementSample(T0 + t, 0.8 if low else 1.0, per_robot=per))
    return out


def step(n: int, kind: str, start: float, end: float, label: str | None = None) -> dict[str, Any]:
    return {"step": n, "kind": kind, "label": label, "start": T0 + start, "end": T0 + end}


def timeline(steps: list[dict[str, Any]] | None = None, **meta: Any) -> plots.Timeline:
    return plots.Timeline.of({"scenario": "s", "steps": steps or [], **meta}, T0, T0 + 10, "x")


def robot_lines(ax: Any) -> list[Line2D]:
    return [line for line in ax.get_lines() if line.get_label() in ROBOTS]


def test_the_agreement_axis_shows_a_robots_dip_to_zero() -> None:
    fig = plots.agreement(agreement_samples(dip=0.0), T0, timeline())
    (ax, *_) = fig.axes
    low, high = ax.get_ylim()
    assert low <= 0.0 and high >= 100.0
    fig = plots.agreement(agreement_samples(dip=0.62), T0, timeline())
    low, high = fig.axes[0].get_ylim()
    # From the lowest value rounded down to ten (60 %), not from 0: the dip stays readable.
    assert 55.0 <= low <= 62.0 and high >= 100.0


def test_the_agreement_lines_of_six_robots_differ_in_colour_and_style() -> None:
    ax = plots.agreement(agreement_samples(), T0, timeline()).axes[0]
    lines = robot_lines(ax)
    assert [line.get_label() for line in lines] == ROBOTS
    colours = {line.get_color() for line in lines}
    styles = {(line.get_linestyle(), line.get_marker()) for line in lines}
    assert len(colours) == 6 and len(styles) == 6
    assert all(line.get_alpha() is None or line.get_alpha() >= 0.8 for line in lines)
    assert "none" not in {str(line.get_marker()).lower() for line in lines}


def test_a_big_fleets_agreement_plot_says_where_the_per_robot_values_are() -> None:
    many = [f"r{i}" for i in range(1, 13)]
    samples = [AgreementSample(T0 + k, 1.0, {r: 1.0 for r in many}) for k in range(5)]
    ax = plots.agreement(samples, T0, timeline()).axes[0]
    labels = ax.get_legend_handles_labels()[1]
    assert not set(labels) & set(many)
    assert any("12 robots" in label and "report.json" in label for label in labels)


def test_the_time_axis_caption_names_only_what_is_drawn() -> None:
    bare = plots.agreement(agreement_samples(), T0, timeline()).axes[0]
    assert "dotted" not in bare.get_xlabel() and "▲" not in bare.get_xlabel()

    steps = [
        step(1, "start", 0.2, 0.8),
        step(2, "mobility", 1.0, 8.0, "walk"),
        step(3, "check", 8.0, 8.1),
        step(4, "partition", 8.5, 8.6),
    ]
    checks = [{"step": 3, "description": "lists agree", "deadline_s": 0.5}]
    tl = timeline(steps, checks=checks)
    ax = plots.agreement(agreement_samples(), T0, tl).axes[0]
    caption = ax.get_xlabel()
    assert "dotted: events" in caption and "▲: check deadlines" in caption
    assert "shaded: walk" in caption
    dotted = sorted(line.get_xdata()[0] for line in ax.get_lines() if line.get_linestyle() == ":")
    # The walk (a mobility step) and the partition are drawn; the run's first start is not.
    assert dotted == [pytest.approx(1.0), pytest.approx(8.5)]
    texts = {t.get_text() for t in ax.texts}
    assert {"walk", "partition"} <= texts
    spans = [(p.get_x(), p.get_width()) for p in ax.patches if isinstance(p, Rectangle)]
    assert spans == [(pytest.approx(1.0), pytest.approx(7.0))]


def test_a_later_start_move_and_link_quality_are_events_too() -> None:
    steps = [
        step(1, "start", 0.2, 0.8),
        step(2, "start", 2.0, 2.5, "r7 joins"),
        step(3, "move", 3.0, 3.1),
        step(4, "quality", 4.0, 4.1),
        step(5, "shape", 5.0, 5.1),
    ]
    tl = timeline(steps)
    assert [(t, label) for t, label, _ in tl.events] == [
        (pytest.approx(2.0), "r7 joins"),
        (pytest.approx(3.0), "move"),
        (pytest.approx(4.0), "link quality"),
        (pytest.approx(5.0), "shaping"),
    ]


def alive(t: float, robot: str, kind: str = "Alive") -> Record:
    return Record(
        t, robot, "tx", "sdfr", "02:00:00:00:00:01", "01:00:5e:7f:ff:fa", "10.0.0.1",
        "239.255.255.250", True, 300, 258, msg_type=kind, robot=robot,
    )  # fmt: skip


def beacons(every: float, duration: float) -> list[Record]:
    """Three robots' Alive datagrams, every `every` seconds, each at its own phase."""
    out = []
    for i, robot in enumerate(("r1", "r2", "r3")):
        t = every * (0.2 + 0.25 * i)
        while t < duration:
            out.append(alive(T0 + t, robot))
            t += every
    return sorted(out, key=lambda r: r.time)


def bar_widths(fig: Any) -> list[float]:
    return [p.get_width() for p in fig.axes[0].patches if isinstance(p, Rectangle)]


@pytest.mark.parametrize(
    ("beacon", "duration"), [(1.0, 20.0), (0.4, 30.0), (10.0, 300.0), (1.0, 120.0), (0.25, 7.0)]
)
def test_datagram_bins_are_whole_beacons(beacon: float, duration: float) -> None:
    recs = beacons(beacon, duration)
    tl = timeline()
    fig = plots.datagrams_per_type(recs, T0, T0 + duration, tl, beacon=beacon)
    widths = bar_widths(fig)
    full = widths[:-1] or widths  # the last bin ends with the run
    width = full[0]
    assert all(w == pytest.approx(width) for w in full)
    assert width / beacon == pytest.approx(round(width / beacon)) and width >= beacon
    assert duration / width <= 60
    assert f"{width:g} s" in fig.axes[0].get_ylabel()
    # Every full bin holds the same number of beacons: no empty bin between full ones.
    heights = [p.get_height() for p in fig.axes[0].patches if isinstance(p, Rectangle)][:-1]
    assert min(heights) > 0


def test_the_beacon_is_read_from_the_run_or_else_from_its_alive_datagrams() -> None:
    from netlab.paper import beacon_period

    assert beacon_period({"beacon_interval_s": 2.0}, []) == 2.0
    # sdfrd's gaps are 0.9 to 1 times its period (`CoreConfig.jitter`).
    rng = random.Random(7)
    for period in (1.0, 0.5, 10.0):
        recs, t = [], 0.0
        while t < 60 * period:
            recs.append(alive(T0 + t, "r1"))
            t += period * rng.uniform(0.9, 1.0)
        assert beacon_period({}, recs) == pytest.approx(period, rel=0.02)
    assert beacon_period({}, [alive(T0, "r1")]) is None
    with pytest.raises(ValueError, match="beacon_interval_s"):
        beacon_period({"beacon_interval_s": 0}, [])


def traffic(rx_kb: list[float], duration: float) -> dict[str, Any]:
    robots = {}
    for i, rx in enumerate(rx_kb, 1):
        tx = 6.0 + i
        robots[f"r{i}"] = {
            "tx_kB": {"payload": tx, "frame": tx * 1.3},
            "rx_kB": {"payload": rx, "frame": rx * 1.3},
            "per_5_min_kB": {
                "tx_payload": tx * 300 / duration,
                "rx_payload": rx * 300 / duration,
            },
        }
    return {"robots": robots, "duration_s": duration}


def footer(fig: Any) -> str:
    """The figure's texts, as one line (they are wrapped to its width)."""
    return " ".join(t.get_text() for t in fig.texts).replace("\n", " ")


def test_a_run_unlike_the_papers_is_not_set_beside_its_figures() -> None:
    from netlab.paper import RunConditions

    cond = RunConditions(robots=3, duration_s=6.8, beacon_s=1.0, services_per_robot=(1, 1))
    assert cond.paper_differences()
    fig = plots.bytes_per_robot(traffic([4.8, 5.2, 7.2], 6.8), cond)
    text = footer(fig)
    for paper in ("220", "320", "540", "850", "over 5 min"):
        assert paper not in text.lower()
    assert "3 robots, 1 s beacon, 1 service each, 6.8 s" in text
    assert "not set beside the paper" in text.lower() and "10 s beacon" in text


def test_a_run_under_the_papers_conditions_is_set_beside_its_figures() -> None:
    from netlab.paper import RunConditions

    cond = RunConditions(robots=4, duration_s=300.0, beacon_s=10.0, services_per_robot=(30, 70))
    assert cond.paper_differences() == []
    text = footer(plots.bytes_per_robot(traffic([600.0, 700.0, 650.0, 640.0], 300.0), cond))
    assert "TX 220-320 kB, RX 540-850 kB" in text
    assert "4 robots, 10 s beacon, 30-70 services each, 300 s" in text


def test_equal_figures_print_one_value_not_a_range() -> None:
    from netlab.paper import RunConditions

    cond = RunConditions(robots=3, duration_s=10.0, beacon_s=1.0, services_per_robot=(2, 2))
    text = footer(plots.bytes_per_robot(traffic([3.82, 3.82, 3.82], 10.0), cond))
    assert "RX 3.8 kB" in text and "3.8-3.8" not in text


@pytest.mark.parametrize(
    ("change", "why"),
    [
        ({"beacon_s": 1.0}, "1 s beacon"),
        ({"robots": 12}, "12 robots"),
        ({"services_per_robot": (2, 2)}, "2 services"),
        ({"services_per_robot": None}, "services per robot unknown"),
        ({"duration_s": 60.0}, "60 s"),
        ({"beacon_s": None}, "beacon unknown"),
    ],
)
def test_each_difference_from_the_paper_is_named(change: dict[str, Any], why: str) -> None:
    from netlab.paper import RunConditions

    base = {"robots": 6, "duration_s": 300.0, "beacon_s": 10.0, "services_per_robot": (70, 70)}
    differences = RunConditions(**{**base, **change}).paper_differences()
    assert len(differences) == 1 and why in differences[0]


def update(t: float, robot: str, version: int, part: int, parts: int, services: int) -> Record:
    return Record(
        t, robot, "tx", "sdfr", "02:00:00:00:00:01", "02:00:00:00:00:02", "10.0.0.1",
        "10.0.0.2", False, 900, 858, msg_type="Update", robot=robot, boot=1, version=version,
        part=part, parts=parts, services=services,
    )  # fmt: skip


def test_services_per_robot_are_counted_from_the_latest_update_of_each() -> None:
    from netlab.paper import RunConditions, run_conditions

    recs = [
        update(T0 + 1, "r1", 1, 0, 1, 3),
        update(T0 + 2, "r1", 2, 0, 2, 20),  # r1 publishes more: 35 in two parts
        update(T0 + 2, "r1", 2, 1, 2, 15),
        update(T0 + 3, "r2", 5, 0, 1, 35),
    ]
    got = run_conditions({"beacon_interval_s": 10.0}, recs, robots=2, duration=300.0)
    assert got == RunConditions(2, 300.0, 10.0, (35, 35))
    # A robot whose services were never seen leaves the count unknown; meta can state it.
    assert run_conditions({}, recs, robots=3, duration=300.0).services_per_robot is None
    stated = run_conditions({"services_per_robot": 50}, [], robots=3, duration=300.0)
    assert stated.services_per_robot == (50, 50)


def test_the_report_keeps_the_paper_out_of_a_run_unlike_it(tmp_path: Path) -> None:
    recs = beacons(1.0, 10.0)
    meta = {"scenario": "s", "start": T0, "duration_s": 10.0, "beacon_interval_s": 1.0}
    conn = [ConnectivitySample(T0 + k, 3, {"r1": 2, "r2": 2, "r3": 2}) for k in range(10)]
    report = write_report(tmp_path, records=recs, connectivity_samples=conn, meta=meta)
    assert "paper_5_min_kB" not in report["traffic"]
    conditions = report["conditions"]
    assert conditions["beacon_s"] == 1.0 and conditions["robots"] == 3
    assert conditions["paper_comparable"] is False and conditions["paper_differences"]
    assert json.loads((tmp_path / "report.json").read_text())["conditions"] == conditions


def test_the_connectivity_plot_shows_stale_pairs_above_the_medium_and_names_its_marks() -> None:
    # The medium links 2 pairs, then 1 after a kill, but 3 still list each other (stale).
    conn = [
        ConnectivitySample(T0 + k, 1 if k >= 3 else 2, {"r1": 2}, reachable_pairs=3)
        for k in range(6)
    ]
    fig = plots.connectivity(conn, T0, T0 + 10, timeline())
    top, bottom = fig.axes[:2]
    assert top.get_ylim()[1] >= 3
    assert bottom.get_xlabel() == "time since start of run (s)"
    killed = timeline([step(1, "start", 0.1, 0.5), step(2, "kill", 3.0, 3.1)])
    fig = plots.connectivity(conn, T0, T0 + 10, killed)
    assert fig.axes[1].get_xlabel() == "time since start of run (s); dotted: events"
    assert [t.get_text() for t in fig.axes[0].texts] == ["kill -9"]
