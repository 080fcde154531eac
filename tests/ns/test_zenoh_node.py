"""The Zenoh peer of the side-by-side bench (`bench.zenoh_node`), for real: three robots of a
netlab lab, each a Zenoh peer with Zenoh's defaults (multicast scouting, gossip), list each
other's services with their attributes, see a new one, a graceful leave, a cut link within
the lease they were given (`--lease-ms`, Zenoh's transport lease) and a kill -9 at once (its
TCP sessions are closed by the kernel: not a silent death to Zenoh).  The churn and the
event log are `bench.peer_node`'s, shared with the python-zeroconf peer."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from bench.listed import own_services, replay
from bench.paper_measure import read_events
from netlab.lab import Lab
from tests.support.fleets import unique_lab_name
from tests.support.waiting import poll

pytestmark = pytest.mark.root

ROOT = Path(__file__).resolve().parents[2]
ROBOTS = ("r1", "r2", "r3")
PUBLISHERS = 5
LEASE_MS = 2000


def events(path: Path) -> list[dict[str, Any]]:
    return read_events([path]) if path.exists() else []


def listed(path: Path) -> set[tuple[str, str]]:
    """What the node lists now (the side-by-side's reading of its seen and gone)."""
    return set().union(*replay(events(path), math.inf).values())


def published(path: Path) -> set[tuple[str, str]]:
    """The services the node (its log is named after it) has up now."""
    robot = path.stem
    return {(robot, sid) for sid in own_services(events(path), robot, math.inf)}


def test_zenoh_peers_list_each_others_services_a_new_one_a_leave_and_a_silent_death(
    tmp_path: Path,
) -> None:
    log = {r: tmp_path / f"{r}.jsonl" for r in ROBOTS}
    with Lab(unique_lab_name(), workdir=tmp_path / "lab") as lab:
        lab.add_robots(list(ROBOTS))
        procs: dict[str, subprocess.Popen[Any]] = {}
        for r in ROBOTS:
            ip = str(lab.robot(r).address.ip)
            argv = [sys.executable, "-m", "bench.zenoh_node", "--robot", r, "--ip", ip,
                    "--publishers", str(PUBLISHERS), "--events", str(log[r]),
                    "--lease-ms", str(LEASE_MS)]  # fmt: skip
            with open(tmp_path / f"{r}.err", "wb") as err:
                procs[r] = lab.popen(r, argv, cwd=ROOT, stderr=err)

        def everyone_lists(robots: tuple[str, ...]) -> bool | str:
            for r in robots:
                want = set().union(*(published(log[o]) for o in robots if o != r))
                if len(want) < PUBLISHERS * (len(robots) - 1) or listed(log[r]) != want:
                    return f"{r} lists {len(listed(log[r]))} of {len(want)}"
            return True

        poll("every peer lists every other's services", lambda: everyone_lists(ROBOTS), 20.0)

        os.kill(procs["r1"].pid, signal.SIGUSR1)  # one more service on r1

        # The signal is handled in r1's own time: wait for its log to say it published.
        def r1_published_it() -> bool:
            return any(sid.startswith("p1001x") for _, sid in published(log["r1"]))

        poll("r1 publishes its new service", r1_published_it, 5.0)
        poll("r1's new service is listed", lambda: everyone_lists(ROBOTS), 5.0)

        os.kill(procs["r3"].pid, signal.SIGTERM)  # a graceful leave: its tokens undeclared
        assert procs["r3"].wait(10) == 0
        assert events(log["r3"])[-1]["op"] == "leave"
        poll("r3's services are gone", lambda: everyone_lists(("r1", "r2")), 5.0)

        # A silent departure: r2's link cut.  Only the lease tells (no FIN comes).
        lab.partition([["r1"], ["r2"]])
        within = 6 * LEASE_MS / 1e3
        took = poll("r2's services are gone on r1", lambda: not listed(log["r1"]), within)
        assert took >= LEASE_MS / 1e3 / 2, f"gone in {took:.2f} s: before the lease could tell"
        lab.merge()
        back = poll("after the merge r1 lists r2's again", lambda: everyone_lists(("r1", "r2")),
                    15.0)  # fmt: skip
        # kill -9 is not silent to Zenoh: the kernel closes the dead process's TCP sessions.
        os.kill(procs["r2"].pid, signal.SIGKILL)
        procs["r2"].wait(5)
        killed = poll("r2's services are gone on r1 after its kill -9",
                      lambda: not listed(log["r1"]), within)  # fmt: skip
        print(
            f"\nzenoh (lease {LEASE_MS} ms): a cut link noticed in {took:.2f} s, listed "
            f"again {back:.2f} s after the merge; a kill -9 noticed in {killed:.2f} s"
        )
        os.kill(procs["r1"].pid, signal.SIGTERM)
        assert procs["r1"].wait(10) == 0
