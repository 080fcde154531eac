"""Issue 4's fleet behaviours that need time, loss or many robots: the bundled scenarios, run
on real sdfrd daemons in netlab, as `netlab run NAME` runs them.

* silent-departure (check 4): kill -9 and a cut link: unreachable on every peer within 3
  beacon periods, kept in history with the connection indicator fallen; both come back;
* partition-merge (check 5): {r1,r2,r3} | {r4,r5,r6}; each side alone within 3 beacons; all
  list all within 1 beacon + 1 s of the merge; no Update datagram in the captures after it;
* lossy (check 7): 30 % loss on every pair: converges, no flap more than once a minute over
  2 minutes, every indicator within 15 points of the round-trip delivery rate, both the
  one the medium's loss allows and the one measured in the captures;
* mobility (check 8): random waypoint, 6 robots, 2 minutes: the lists agree with the
  medium's truth >= 95 % of the time with a 1-beacon lag;
  (lossy and mobility run side by side, each on its own lab, to keep CI's wall time down);
* scale-50 (check 10): 50 robots at the product's 10 s beacon converge and stay converged
  for a minute; CPU and memory per daemon measured.

A failed check says which robot missed what (the run's summary is the failure message), and
the run folder -- pcaps of every robot and the medium, run.json, report.json, plots, daemon
logs -- is kept under runs/tests/ for inspection; a passing run's folder is removed unless
SDFR_KEEP_RUNS=1.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable, Mapping
from pathlib import Path

import pytest

from netlab import scenario
from netlab.analysis import ping_delivery
from netlab.pcap import read_run
from tests.support.fleets import discard, run_folder

pytestmark = pytest.mark.root


Inspect = Callable[[scenario.RunResult, Path], None]


def run_bundled(
    *names: str, inspect: Mapping[str, Inspect] | None = None
) -> list[scenario.RunResult]:
    """Run bundled scenarios in full -- several at the same time, each on its own lab (its own
    namespaces, medium and captures) -- and fail with the summary of each that did not pass,
    keeping its folder.  `inspect[name](result, folder)` looks further into a passed run
    before its folder goes."""
    runs: dict[str, tuple[scenario.RunResult, Path]] = {}

    def one(name: str) -> None:
        sc = scenario.load(scenario.find(name))
        folder = run_folder(name)
        say = print if len(names) == 1 else (lambda line: print(f"[{name}] {line}", flush=True))
        runs[name] = (scenario.run(sc, run_dir=folder, quick=False, say=say), folder)

    threads = [threading.Thread(target=one, args=(n,), name=f"scenario-{n}") for n in names]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    failures = []
    for name in names:
        if name not in runs:
            failures.append(f"scenario {name} did not finish (its thread raised; see above)")
            continue
        result, folder = runs[name]
        if result.status == "skipped":
            failures.append(f"{name} was skipped: {result.reason}")
        elif not result.ok:
            failures.append(
                "\n".join([f"scenario {name} {result.status}:", *result.summary()])
                + f"\nrun folder kept for inspection: {folder} (pcaps, run.json, report.json, "
                "logs/)"
            )
    if failures:
        pytest.fail("\n\n".join(failures), pytrace=False)
    for name in names:
        result, folder = runs[name]
        if inspect is not None and name in inspect:
            try:
                inspect[name](result, folder)
            except BaseException:
                print(f"run folder kept for inspection: {folder}")
                raise
    for _, folder in runs.values():
        discard(folder)
    return [runs[n][0] for n in names]


def check(result: scenario.RunResult, kind: str) -> scenario.CheckResult:
    found = [c for c in result.checks if c.kind == kind]
    assert found, f"{result.scenario} has no {kind} check"
    return found[-1]


def test_silent_departure() -> None:
    (result,) = run_bundled("silent-departure")
    kinds = [c.kind for c in result.checks]
    assert kinds.count("unreachable") == 2 and kinds.count("history") == 2


def test_partition_and_merge() -> None:
    (result,) = run_bundled("partition-merge")
    updates = check(result, "updates")
    assert updates.ok is True and updates.detail.startswith("0 Update datagrams"), updates.detail


def test_lossy_links_and_mobility_side_by_side() -> None:
    """Checks 7 (30 % loss) and 8 (random waypoint), two minutes each, run at the same time
    on two labs: the suite's wall time in CI counts, and neither fleet hears the other."""

    def measured(result: scenario.RunResult, folder: Path) -> None:
        # The true delivery rate, measured on the air: of the pings each robot sent a peer
        # during the lossy window, the share whose reply reached it (ARP delays included).
        meta = json.loads((folder / "run.json").read_text())["meta"]
        (window,) = [s for s in meta["steps"] if s["label"] == "lossy"]
        tally = ping_delivery(read_run(folder), since=window["start"], until=window["end"])
        ind = check(result, "indicator").data["indicators"]
        far = []
        for (a, b), t in tally.items():
            assert t.sent >= 150, (a, b, t)  # one ping each 0.5 s for 2 minutes
            if ind[a].get(b) is None or abs(ind[a][b] - (t.rate or 0.0)) > 0.15:
                far.append(f"{a} rates {b} at {ind[a].get(b)}, measured {t.rate:.2f}")
        assert len(tally) == 30 and not far, far
        rates = sorted(t.rate or 0.0 for t in tally.values())
        print(f"lossy: measured round-trip delivery {rates[0]:.2f}-{rates[-1]:.2f} per pair")

    result, walk = run_bundled("lossy", "mobility", inspect={"lossy": measured})
    flaps = check(result, "flaps")
    assert flaps.data["flaps"]["samples"] >= 300, flaps.detail  # two minutes, sampled
    ind = check(result, "indicator")
    assert ind.data["abs_error"]["pairs"] == 30, ind.data
    print(f"lossy: {flaps.detail}; indicators: {ind.detail}")

    agree = next(c for c in walk.checks if c.kind == "agreement")
    share = agree.data["agreement"]["pair_share"]
    assert share >= 0.95
    print(f"mobility: agreement {share:.1%} with a 1-beacon lag ({agree.detail})")


def test_fifty_robots_converge_and_stay_converged() -> None:
    (result,) = run_bundled("scale-50")
    res = check(result, "resources")
    assert res.ok is True and res.data["daemons"] == 50, res.detail
    # (Each daemon one process: its layers are threads, sdfrd's default.)
    assert all(u["processes"] == 1 for u in res.data["per_daemon"].values()), res.data
    print(f"scale-50: {res.detail}")
