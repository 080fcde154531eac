"""bench.traffic's table: an idle fleet of two services per robot is not the paper's load, so
the paper's figure 6 is not set beside it (issue 26: compare like with like)."""

from __future__ import annotations

from bench import traffic
from netlab import paper


def _entry(robots: int) -> dict[str, object]:
    one = {s: traffic.spread([7.0, 7.4]) for s in traffic.SIZES}
    return {"robots": robots, "per_5_min_kB": {"tx": one, "rx": one}, "status": "passed"}


def test_the_idle_fleet_table_sets_no_paper_figure_beside_its_own() -> None:
    text = traffic.table([_entry(2), _entry(6)])
    lo, hi = paper.PAPER_TX_KB_5MIN
    assert f"{lo}-{hi}" not in text and "factor" not in text
    assert "not the paper's load" in text and paper.PAPER_CONDITIONS in text
    rows = text.splitlines()[3:]
    assert [r.split()[0] for r in rows] == ["2", "6"]
    assert all("7-7 (7-7)" in r for r in rows)
