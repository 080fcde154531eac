"""The ROS 2 / DDS peer of the side-by-side bench (`bench.dds_node`), for real: three robots of
a netlab lab, each a ROS 2 node on Fast DDS (UDPv4 only, so everything goes over the lab's
medium) with the ROS 2 interpreter of this tier, list each other's services with their
attributes, see a new one and a graceful leave at once, and a cut link and a kill -9 within
the participants' lease (`--lease-s`, set through a Fast DDS XML profile), never before half
of it.  The churn and the event log are `bench.peer_node`'s, shared with the other peers."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from netlab.lab import Lab
from tests.support.fleets import unique_lab_name
from tests.support.peers import Nodes
from tests.support.waiting import poll

pytestmark = pytest.mark.root

ROBOTS = ("r1", "r2", "r3")
PUBLISHERS = 5
LEASE_S = 3.0


def test_dds_peers_list_each_others_services_a_new_one_a_leave_and_a_silent_death(
    tmp_path: Path, ros2_env: Path
) -> None:
    with Lab(unique_lab_name(), workdir=tmp_path / "lab") as lab:
        lab.add_robots(list(ROBOTS))
        nodes = Nodes(lab, ROBOTS, tmp_path, PUBLISHERS)
        nodes.start(lambda r, ip, log: [
            str(ros2_env), "-m", "bench.dds_node", "--robot", r, "--ip", ip,
            "--publishers", str(PUBLISHERS), "--events", str(log), "--lease-s", str(LEASE_S),
        ])  # fmt: skip
        procs = nodes.procs
        try:
            nodes.meet_add_and_leave(30.0, 5.0, 10.0)  # r3's leave: the node destroyed
            gone = poll("r3's services are gone", lambda: nodes.everyone_lists(("r1", "r2")),
                        LEASE_S / 2)  # fmt: skip

            # A cut link is silent: only the lease tells; kill -9 too (DDS is UDP only).
            took, back, killed = nodes.cut_merge_kill(LEASE_S, 20.0)
            assert killed >= LEASE_S / 2, f"gone in {killed:.2f} s: before the lease could tell"
            print(
                f"\ndds (lease {LEASE_S} s): a leave noticed in {gone:.2f} s, a cut link in "
                f"{took:.2f} s, listed again {back:.2f} s after the merge; a kill -9 noticed "
                f"in {killed:.2f} s"
            )
            os.kill(procs["r1"].pid, signal.SIGTERM)
            assert procs["r1"].wait(10) == 0
        finally:
            nodes.close()
