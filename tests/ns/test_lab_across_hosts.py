"""A lab across hosts, for real: two simulated hosts (namespaces with their own sshd, reached
over SSH), each running its share of the lab (`Lab(span=...)`: its robots with real sdfrd,
the other host's robots known by MAC and position) on media joined by VXLAN.  The four
robots find each other across hosts, a partition along the hosts' line cuts each side off
within the same bounds as on one host, and the merge brings all back."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from netlab import hostsim, kernel, naming
from netlab.hostsim import SimHosts

pytestmark = pytest.mark.root

REPO = Path(__file__).resolve().parents[2]
BEACON = 1.0

# A host's share of the lab, run over ssh; then per stdin line a JSON command:
# ["lists"] (each robot's listing), ["partition", groups], ["merge"], or "down".
PART = r"""
import json, sys
from pathlib import Path
from netlab import naming
from netlab.lab import Lab
from netlab.vxlan import span_of
from tests.support.radio import listed
cfg = json.loads(sys.argv[1])
span = span_of(cfg["lab"], cfg["local"], cfg["hosts"], vni=cfg["vni"])
with Lab(cfg["name"], seed=7, fleet=3, span=span, workdir=Path(cfg["workdir"])) as lab:
    for robot, index in cfg["mine"].items():
        lab.add_robot(robot, index=index, pos=(5.0 * index, 0.0))
    for robot, index in cfg["theirs"].items():
        lab.add_remote(robot, mac=naming.mac_for(7, index), pos=(5.0 * index, 0.0))
    lab.start_all(beacon_interval=float(cfg["beacon"]))
    print(json.dumps("ready"), flush=True)
    for line in sys.stdin:
        cmd = json.loads(line)
        if cmd == "down":
            break
        if cmd[0] == "lists":
            print(json.dumps({r: sorted(listed(lab, r)) for r in cfg["mine"]}), flush=True)
        elif cmd[0] == "partition":
            lab.partition(cmd[1])
            print(json.dumps("ok"), flush=True)
        elif cmd[0] == "merge":
            lab.merge()
            print(json.dumps("ok"), flush=True)
"""


class Part:
    """One host's share of the lab, driven over its ssh session's stdin and stdout."""

    def __init__(self, sim: SimHosts, alias: str, cfg: dict[str, object]) -> None:
        argv = ["env", f"PYTHONPATH={REPO}", sys.executable, "-c", PART, json.dumps(cfg)]
        self.alias = alias
        self.proc = subprocess.Popen(
            sim.ssh_argv(alias, argv),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )

    def ask(self, cmd: object) -> object:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        if cmd is not None:
            self.proc.stdin.write(json.dumps(cmd) + "\n")
            self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            err = self.proc.stderr.read() if self.proc.stderr else ""
            raise AssertionError(f"host {self.alias}'s share of the lab ended: {err[-2000:]}")
        return json.loads(line)

    def down(self) -> None:
        assert self.proc.stdin is not None
        if self.proc.poll() is None:
            self.proc.stdin.write(json.dumps("down") + "\n")
            self.proc.stdin.close()
        try:
            self.proc.wait(60)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)


@pytest.fixture
def parts(tmp_path: Path) -> Iterator[tuple[Part, Part]]:
    missing = hostsim.needs()
    assert not missing, f"simulated hosts need {missing}: scripts/bootstrap.sh installs them"
    with SimHosts(naming.unique_lab_name("h"), 2, tmp_path / "hosts") as sim:
        lab = naming.unique_lab_name("x")
        names = [naming.unique_lab_name("x"), naming.unique_lab_name("x")]
        shares = [{"r1": 0, "r2": 1}, {"r3": 2, "r4": 3}]
        started: list[Part] = []
        try:
            for i, host in enumerate(sim.hosts):
                cfg = {
                    "lab": lab,
                    "name": names[i],
                    "local": host.address,
                    "hosts": [h.address for h in sim.hosts],
                    "vni": 4243,
                    "mine": shares[i],
                    "theirs": shares[1 - i],
                    "beacon": BEACON,
                    "workdir": str(tmp_path / names[i]),
                }
                started.append(Part(sim, host.alias, cfg))
            for part in started:
                assert part.ask(None) == "ready"
            yield started[0], started[1]
        finally:
            for part in started:
                part.down()
        left = [ns for ns in kernel.list_ns() if any(ns.startswith(f"nl-{n}-") for n in names)]
        assert not left, f"namespaces left: {left}"


def listing(parts: tuple[Part, Part]) -> dict[str, set[str]]:
    out: dict[str, set[str]] = {}
    for part in parts:
        got = part.ask(["lists"])
        assert isinstance(got, dict)
        out.update({r: set(v) for r, v in got.items()})
    return out


def until(what: str, ok: Callable[[], bool], within: float) -> float:
    t0 = time.monotonic()
    while not ok():
        if time.monotonic() - t0 > within:
            raise AssertionError(f"not within {within:.1f} s: {what}")
        time.sleep(0.1)
    return time.monotonic() - t0


def test_robots_on_two_hosts_find_each_other_split_along_the_hosts_and_merge(
    parts: tuple[Part, Part],
) -> None:
    everyone = {"r1", "r2", "r3", "r4"}
    sides = [["r1", "r2"], ["r3", "r4"]]
    all_all = until(
        "every robot lists the three others, across hosts",
        lambda: all(v == everyone - {r} for r, v in listing(parts).items()),
        30 * BEACON,
    )
    for part in parts:
        assert part.ask(["partition", sides]) == "ok"
    split = until(
        "each robot lists only its own host's other robot",
        lambda: all(v == set(s) - {r} for s in sides for r, v in listing(parts).items() if r in s),
        3 * BEACON + 1.5,  # as on one host (fleet-behaviour.md, row 5)
    )
    for part in parts:
        assert part.ask(["merge"]) == "ok"
    merged = until(
        "after the merge every robot lists the three others again",
        lambda: all(v == everyone - {r} for r, v in listing(parts).items()),
        BEACON + 2.0,
    )
    print(f"\nacross 2 hosts: all list all {all_all:.2f} s after start; split seen in "
          f"{split:.2f} s; merged in {merged:.2f} s (beacon {BEACON:.0f} s)")  # fmt: skip
