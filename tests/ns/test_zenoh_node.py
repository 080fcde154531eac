"""The Zenoh peer of the side-by-side bench (`bench.zenoh_node`), for real: three robots of a
netlab lab, each a Zenoh peer with Zenoh's defaults (multicast scouting, gossip), list each
other's services with their attributes, see a new one, a graceful leave, a cut link within
the lease they were given (`--lease-ms`, Zenoh's transport lease) and a kill -9 at once (its
TCP sessions are closed by the kernel: not a silent death to Zenoh).  The churn and the
event log are `bench.peer_node`'s, shared with the other peers."""

from __future__ import annotations

import os
import signal
import sys
from pathlib import Path

import pytest

from netlab.lab import Lab
from tests.support.fleets import unique_lab_name
from tests.support.peers import Nodes
from tests.support.waiting import poll

pytestmark = pytest.mark.root

ROBOTS = ("r1", "r2", "r3")
PUBLISHERS = 5
LEASE_MS = 2000


def test_zenoh_peers_list_each_others_services_a_new_one_a_leave_and_a_silent_death(
    tmp_path: Path,
) -> None:
    with Lab(unique_lab_name(), workdir=tmp_path / "lab") as lab:
        lab.add_robots(list(ROBOTS))
        nodes = Nodes(lab, ROBOTS, tmp_path, PUBLISHERS)
        nodes.start(lambda r, ip, log: [
            sys.executable, "-m", "bench.zenoh_node", "--robot", r, "--ip", ip,
            "--publishers", str(PUBLISHERS), "--events", str(log), "--lease-ms", str(LEASE_MS),
        ])  # fmt: skip
        procs = nodes.procs
        try:
            nodes.meet_add_and_leave(20.0, 5.0, 10.0)  # r3's leave: its tokens undeclared
            poll("r3's services are gone", lambda: nodes.everyone_lists(("r1", "r2")), 5.0)

            # A cut link is silent (no FIN comes): only the lease tells.  kill -9 is not silent
            # to Zenoh: the kernel closes the dead process's TCP sessions.
            took, back, killed = nodes.cut_merge_kill(LEASE_MS / 1e3, 15.0)
            print(
                f"\nzenoh (lease {LEASE_MS} ms): a cut link noticed in {took:.2f} s, listed "
                f"again {back:.2f} s after the merge; a kill -9 noticed in {killed:.2f} s"
            )
            os.kill(procs["r1"].pid, signal.SIGTERM)
            assert procs["r1"].wait(10) == 0
        finally:
            nodes.close()
