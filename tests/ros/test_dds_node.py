"""The ROS 2 / DDS peer of the side-by-side bench (`bench.dds_node`), for real: three robots of
a netlab lab, each a ROS 2 node on Fast DDS (UDPv4 only, so everything goes over the lab's
medium) with the ROS 2 interpreter of this tier, list each other's services with their
attributes, see a new one and a graceful leave at once, and a cut link and a kill -9 within
the participants' lease (`--lease-s`, set through a Fast DDS XML profile), never before half
of it.  The churn and the event log are `bench.peer_node`'s, shared with the other peers."""

from __future__ import annotations

import math
import os
import signal
import subprocess
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
LEASE_S = 3.0


def events(path: Path) -> list[dict[str, Any]]:
    return read_events([path]) if path.exists() else []


def listed(path: Path) -> set[tuple[str, str]]:
    """What the node lists now (the side-by-side's reading of its seen and gone)."""
    return set().union(*replay(events(path), math.inf).values())


def published(path: Path) -> set[tuple[str, str]]:
    robot = path.stem
    return {(robot, sid) for sid in own_services(events(path), robot, math.inf)}


def test_dds_peers_list_each_others_services_a_new_one_a_leave_and_a_silent_death(
    tmp_path: Path, ros2_env: Path
) -> None:
    log = {r: tmp_path / f"{r}.jsonl" for r in ROBOTS}
    with Lab(unique_lab_name(), workdir=tmp_path / "lab") as lab:
        lab.add_robots(list(ROBOTS))
        procs: dict[str, subprocess.Popen[Any]] = {}
        for r in ROBOTS:
            ip = str(lab.robot(r).address.ip)
            argv = [str(ros2_env), "-m", "bench.dds_node", "--robot", r, "--ip", ip,
                    "--publishers", str(PUBLISHERS), "--events", str(log[r]),
                    "--lease-s", str(LEASE_S)]  # fmt: skip
            with open(tmp_path / f"{r}.err", "wb") as err:
                procs[r] = lab.popen(r, argv, cwd=ROOT, stderr=err)

        def everyone_lists(robots: tuple[str, ...]) -> bool | str:
            for r in robots:
                if procs[r].poll() is not None:
                    err = (tmp_path / f"{r}.err").read_text()[-2000:]
                    raise AssertionError(f"{r}'s node ended ({procs[r].returncode}): {err}")
                want = set().union(*(published(log[o]) for o in robots if o != r))
                if len(want) < PUBLISHERS * (len(robots) - 1) or listed(log[r]) != want:
                    return f"{r} lists {len(listed(log[r]))} of {len(want)}"
            return True

        try:
            poll("every peer lists every other's services", lambda: everyone_lists(ROBOTS), 30.0)

            os.kill(procs["r1"].pid, signal.SIGUSR1)  # one more service on r1

            def r1_published_it() -> bool:
                return any(sid.startswith("p1001x") for _, sid in published(log["r1"]))

            poll("r1 publishes its new service", r1_published_it, 5.0)
            poll("r1's new service is listed", lambda: everyone_lists(ROBOTS), 5.0)

            os.kill(procs["r3"].pid, signal.SIGTERM)  # a graceful leave: the node destroyed
            assert procs["r3"].wait(10) == 0
            assert events(log["r3"])[-1]["op"] == "leave"
            gone = poll("r3's services are gone", lambda: everyone_lists(("r1", "r2")),
                        LEASE_S / 2)  # fmt: skip

            # A silent departure: r2's link cut.  Only the lease tells.
            lab.partition([["r1"], ["r2"]])
            within = 6 * LEASE_S
            took = poll("r2's services are gone on r1", lambda: not listed(log["r1"]), within)
            assert took >= LEASE_S / 2, f"gone in {took:.2f} s: before the lease could tell"
            lab.merge()
            back = poll("after the merge r1 lists r2's again",
                        lambda: everyone_lists(("r1", "r2")), 20.0)  # fmt: skip
            os.kill(procs["r2"].pid, signal.SIGKILL)  # silent to DDS too (UDP only)
            procs["r2"].wait(5)
            killed = poll("r2's services are gone on r1 after its kill -9",
                          lambda: not listed(log["r1"]), within)  # fmt: skip
            assert killed >= LEASE_S / 2, f"gone in {killed:.2f} s: before the lease could tell"
            print(
                f"\ndds (lease {LEASE_S} s): a leave noticed in {gone:.2f} s, a cut link in "
                f"{took:.2f} s, listed again {back:.2f} s after the merge; a kill -9 noticed "
                f"in {killed:.2f} s"
            )
            os.kill(procs["r1"].pid, signal.SIGTERM)
            assert procs["r1"].wait(10) == 0
        finally:
            for proc in procs.values():
                if proc.poll() is None:
                    proc.kill()
                    proc.wait(5)
            for r in ROBOTS:
                errors = tmp_path / f"{r}.err"
                if errors.exists():
                    print(f"--- {r}'s stderr\n{errors.read_text()[-1500:]}")
