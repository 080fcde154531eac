"""The Avahi peer of the side-by-side bench (`bench.avahi_node`), for real: three robots of a
netlab lab, each with its own avahi-daemon on its own D-Bus (Debian's avahi-daemon and
avahi-utils, installed by scripts/avahi-setup.sh when missing), publish with avahi-publish and
list each other's services with avahi-browse, see a new one and a graceful leave (Avahi's
goodbyes), and go on listing a robot killed with kill -9 (mDNS has no liveness: its records
live 75 minutes).  Nothing of a robot's Avahi outlives its node."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from netlab.lab import Lab
from tests.support.fleets import unique_lab_name
from tests.support.peers import ROOT, Nodes, listed
from tests.support.waiting import poll

pytestmark = pytest.mark.root

ROBOTS = ("r1", "r2", "r3")
PUBLISHERS = 5


@pytest.fixture(scope="module")
def avahi() -> None:
    res = subprocess.run(["bash", "scripts/avahi-setup.sh"], cwd=ROOT, capture_output=True,
                         text=True, timeout=600, stdin=subprocess.DEVNULL)  # fmt: skip
    if res.returncode != 0:
        pytest.fail(f"scripts/avahi-setup.sh failed, so Avahi cannot run:\n{res.stderr}")


def daemons_of(tmp_path: Path) -> list[str]:
    """The processes on a bus of this test (its robots' D-Bus sockets are under tmp_path):
    their daemons, publishers and browsers."""
    found = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            env = (proc / "environ").read_bytes()
            args = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if str(tmp_path).encode() in env or str(tmp_path) in args:
            found.append(f"{proc.name}: {args}")
    return found


def test_avahi_peers_list_each_others_services_a_new_one_a_leave_and_keep_a_dead_one(
    tmp_path: Path, avahi: None
) -> None:
    with Lab(unique_lab_name(), workdir=tmp_path / "lab") as lab:
        lab.add_robots(list(ROBOTS))
        nodes = Nodes(lab, ROBOTS, tmp_path, PUBLISHERS)
        nodes.start(lambda r, ip, log: [
            sys.executable, "-m", "bench.avahi_node", "--robot", r, "--ip", ip,
            "--publishers", str(PUBLISHERS), "--events", str(log),
        ])  # fmt: skip
        procs, log = nodes.procs, nodes.log
        try:
            nodes.meet_add_and_leave(60.0, 15.0, 20.0)  # r3's leave: mDNS goodbyes
            poll("r3's services are gone", lambda: nodes.everyone_lists(("r1", "r2")), 10.0)

            # kill -9: the node's daemon and publishers die with it (no goodbye), and r1 goes
            # on listing r2's services: mDNS has no notion of a robot gone silent.
            had = listed(log["r1"])
            os.kill(procs["r2"].pid, signal.SIGKILL)
            procs["r2"].wait(5)
            time.sleep(5.0)
            assert listed(log["r1"]) == had and had
            os.kill(procs["r1"].pid, signal.SIGTERM)
            assert procs["r1"].wait(20) == 0
            poll("no Avahi process of this test is left", lambda: not daemons_of(tmp_path), 10.0)
        finally:
            nodes.close()
