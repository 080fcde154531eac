"""The Avahi peer of the side-by-side bench (`bench.avahi_node`), for real: three robots of a
netlab lab, each with its own avahi-daemon on its own D-Bus (Debian's avahi-daemon and
avahi-utils, installed by scripts/avahi-setup.sh when missing), publish with avahi-publish and
list each other's services with avahi-browse, see a new one and a graceful leave (Avahi's
goodbyes), and go on listing a robot killed with kill -9 (mDNS has no liveness: its records
live 75 minutes).  Nothing of a robot's Avahi outlives its node."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
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


def events(path: Path) -> list[dict[str, Any]]:
    return read_events([path]) if path.exists() else []


def listed(path: Path) -> set[tuple[str, str]]:
    return set().union(*replay(events(path), math.inf).values())


def published(path: Path) -> set[tuple[str, str]]:
    robot = path.stem
    return {(robot, sid) for sid in own_services(events(path), robot, math.inf)}


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
    log = {r: tmp_path / f"{r}.jsonl" for r in ROBOTS}
    with Lab(unique_lab_name(), workdir=tmp_path / "lab") as lab:
        lab.add_robots(list(ROBOTS))
        procs: dict[str, subprocess.Popen[Any]] = {}
        for r in ROBOTS:
            ip = str(lab.robot(r).address.ip)
            argv = [sys.executable, "-m", "bench.avahi_node", "--robot", r, "--ip", ip,
                    "--publishers", str(PUBLISHERS), "--events", str(log[r])]  # fmt: skip
            with open(tmp_path / f"{r}.err", "wb") as err:
                procs[r] = lab.popen(r, argv, cwd=ROOT, stderr=err)

        def everyone_lists(robots: tuple[str, ...]) -> bool | str:
            for r in robots:
                if procs[r].poll() is not None:
                    said = (tmp_path / f"{r}.err").read_text()[-2000:]
                    raise AssertionError(f"{r}'s node ended ({procs[r].returncode}): {said}")
                want = set().union(*(published(log[o]) for o in robots if o != r))
                if len(want) < PUBLISHERS * (len(robots) - 1) or listed(log[r]) != want:
                    return f"{r} lists {len(listed(log[r]))} of {len(want)}"
            return True

        try:
            poll("every peer lists every other's services", lambda: everyone_lists(ROBOTS), 60.0)

            os.kill(procs["r1"].pid, signal.SIGUSR1)  # one more service on r1

            def r1_published_it() -> bool:
                return any(sid.startswith("p1001x") for _, sid in published(log["r1"]))

            poll("r1 publishes its new service", r1_published_it, 5.0)
            poll("r1's new service is listed", lambda: everyone_lists(ROBOTS), 15.0)

            os.kill(procs["r3"].pid, signal.SIGTERM)  # a graceful leave: goodbyes
            assert procs["r3"].wait(20) == 0
            assert events(log["r3"])[-1]["op"] == "leave"
            poll("r3's services are gone", lambda: everyone_lists(("r1", "r2")), 10.0)

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
            for proc in procs.values():
                if proc.poll() is None:
                    proc.kill()
                    proc.wait(5)
            for r in ROBOTS:
                errors = tmp_path / f"{r}.err"
                if errors.exists():
                    print(f"--- {r}'s stderr\n{errors.read_text()[-1500:]}")
