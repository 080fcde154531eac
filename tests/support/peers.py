"""What the tests of the side-by-side's peer nodes share (tests/ns/test_zenoh_node.py,
tests/ns/test_avahi_node.py, tests/ros/test_dds_node.py): a node's event log read the way the
bench reads it, the nodes started in a lab, and the wait for every robot to list every other's
services."""

from __future__ import annotations

import math
import os
import signal
import subprocess
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from bench.listed import own_services, replay
from bench.paper_measure import read_events
from netlab.lab import Lab
from tests.support.waiting import poll

ROOT = Path(__file__).resolve().parents[2]


def events(path: Path) -> list[dict[str, Any]]:
    return read_events([path]) if path.exists() else []


def listed(path: Path) -> set[tuple[str, str]]:
    """What the node lists now (the side-by-side's reading of its seen and gone)."""
    return set().union(*replay(events(path), math.inf).values())


def published(path: Path) -> set[tuple[str, str]]:
    """The services the node (its log is named after its robot) has up now."""
    robot = path.stem
    return {(robot, sid) for sid in own_services(events(path), robot, math.inf)}


class Nodes:
    """One node a robot, each with its event log (`log[robot]`) and its stderr in `folder`."""

    def __init__(self, lab: Lab, robots: Sequence[str], folder: Path, publishers: int) -> None:
        self.lab = lab
        self.folder = folder
        self.publishers = publishers
        self.log = {r: folder / f"{r}.jsonl" for r in robots}
        self.procs: dict[str, subprocess.Popen[Any]] = {}

    def start(self, argv: Callable[[str, str, Path], list[str]]) -> None:
        """`argv(robot, its address, its event log)` on every robot."""
        for r, log in self.log.items():
            ip = str(self.lab.robot(r).address.ip)
            with open(self.folder / f"{r}.err", "wb") as err:
                self.procs[r] = self.lab.popen(r, argv(r, ip, log), cwd=ROOT, stderr=err)

    def stderr(self, robot: str) -> str:
        path = self.folder / f"{robot}.err"
        return path.read_text(errors="replace") if path.exists() else ""

    def everyone_lists(self, robots: Sequence[str]) -> bool | str:
        """Whether each of `robots` lists exactly the others' services (a poll's predicate:
        what is missing, else True); a node that ended fails at once, with its stderr."""
        for r in robots:
            if self.procs[r].poll() is not None:
                raise AssertionError(
                    f"{r}'s node ended ({self.procs[r].returncode}): {self.stderr(r)[-2000:]}"
                )
            want = set().union(*(published(self.log[o]) for o in robots if o != r))
            got = listed(self.log[r])
            if len(want) < self.publishers * (len(robots) - 1) or got != want:
                return f"{r} lists {len(got)} of {len(want)}"
        return True

    def published_extra(self, robot: str) -> bool:
        """Whether `robot` has published the service SIGUSR1 asked for (``p1001x...``)."""
        return any(sid.startswith("p1001x") for _, sid in published(self.log[robot]))

    def meet_add_and_leave(self, meet: float, add: float, leave: float) -> None:
        """The script every peer node follows first: each robot lists every other's services
        (within `meet` s); SIGUSR1 gives r1 one more service, listed by all within `add` s;
        SIGTERM makes r3 leave gracefully (its node exits 0 within `leave` s, its log's last
        event a leave).  What the leave looks like to the others is the test's to judge."""
        robots = list(self.log)
        poll("every peer lists every other's services", lambda: self.everyone_lists(robots), meet)
        os.kill(self.procs["r1"].pid, signal.SIGUSR1)  # one more service on r1
        # The signal is handled in r1's own time: wait for its log to say it published.
        poll("r1 publishes its new service", lambda: self.published_extra("r1"), 5.0)
        poll("r1's new service is listed", lambda: self.everyone_lists(robots), add)
        os.kill(self.procs["r3"].pid, signal.SIGTERM)
        assert self.procs["r3"].wait(leave) == 0
        assert events(self.log["r3"])[-1]["op"] == "leave"

    def cut_merge_kill(self, lease: float, back: float) -> tuple[float, float, float]:
        """What only a lease can tell, on a system that has one: r2's link cut (no goodbye
        comes), so r1 drops r2's services within 6 leases, not before half of one; the merge,
        r1 listing them again within `back` s; then r2's node killed (-9) and r1 dropping its
        services within 6 leases.  The seconds each took."""
        lab, log = self.lab, self.log
        lab.partition([["r1"], ["r2"]])
        within = 6 * lease
        took = poll("r2's services are gone on r1", lambda: not listed(log["r1"]), within)
        assert took >= lease / 2, f"gone in {took:.2f} s: before the lease could tell"
        lab.merge()
        again = poll("after the merge r1 lists r2's again",
                     lambda: self.everyone_lists(("r1", "r2")), back)  # fmt: skip
        os.kill(self.procs["r2"].pid, signal.SIGKILL)
        self.procs["r2"].wait(5)
        killed = poll("r2's services are gone on r1 after its kill -9",
                      lambda: not listed(log["r1"]), within)  # fmt: skip
        return took, again, killed

    def close(self) -> None:
        """Kill what still runs; print each node's stderr (the test's output on a failure)."""
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait(5)
        for r in self.log:
            print(f"--- {r}'s stderr\n{self.stderr(r)[-1500:]}")
