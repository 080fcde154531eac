"""A medium across hosts (netlab.vxlan, Medium.span) on simulated hosts reached over SSH: each
host makes its own medium and robot, joined to the other's by one VXLAN with head-end
replication; ARP's broadcast and unicast cross it, and each pair's verdict is applied on the
receiving host only (a cut there stops the pair, the sender's host unchanged)."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from netlab import hostsim, kernel, naming
from netlab.hostsim import SimHosts

pytestmark = pytest.mark.root

REPO = Path(__file__).resolve().parents[2]

# Run on a host over ssh: its medium (spanned) and one robot; then, per stdin line, a JSON
# list of the links to load ([sender, receiver] pairs) or "down".
HOST = r"""
import json, sys
from netlab import kernel
from netlab.medium import Medium
from netlab.vxlan import span_of
import ipaddress
cfg = json.loads(sys.argv[1])
medium = Medium(f"nl-{cfg['lab']}-air")
robot_ns = f"nl-{cfg['lab']}-{cfg['robot']}"
try:
    medium.create()
    medium.span(span_of(cfg["lab"], cfg["local"], cfg["hosts"], vni=cfg["vni"]))
    kernel.create_ns(robot_ns).close()
    medium.attach(robot_ns, f"v{cfg['robot']}", cfg["mac"])
    kernel.bring_up(robot_ns, "eth0", ipaddress.IPv4Interface(cfg["address"]), "robot", 1450)
    ports = {cfg["robot"]: f"v{cfg['robot']}"}
    print("ready", flush=True)
    for line in sys.stdin:
        if line.strip() == "down":
            break
        links = {tuple(p): 0.0 for p in json.loads(line)}
        medium.load(links, ports, remote=cfg["remote"])
        print("loaded", flush=True)
finally:
    medium.close()
    kernel.remove_ns(robot_ns)
    kernel.remove_ns(medium.ns)
"""


class Host:
    """One host's medium and robot, run over ssh; `load` sends it links."""

    def __init__(self, hosts: SimHosts, alias: str, cfg: dict[str, object]) -> None:
        argv = [sys.executable, "-c", HOST, json.dumps(cfg)]
        self.proc = subprocess.Popen(
            hosts.ssh_argv(alias, ["env", f"PYTHONPATH={REPO}", *argv]),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.expect("ready")

    def expect(self, word: str) -> None:
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline().strip()
        if line != word:
            self.proc.kill()
            raise AssertionError(f"expected {word!r}, got {line!r}: {self.proc.stderr.read()}")  # type: ignore[union-attr]

    def load(self, pairs: list[tuple[str, str]]) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps(pairs) + "\n")
        self.proc.stdin.flush()
        self.expect("loaded")

    def down(self) -> None:
        assert self.proc.stdin is not None
        if self.proc.poll() is None:
            self.proc.stdin.write("down\n")
            self.proc.stdin.close()
        assert self.proc.wait(30) == 0, self.proc.stderr.read()  # type: ignore[union-attr]


@pytest.fixture
def two_hosts(tmp_path: Path) -> Iterator[tuple[SimHosts, list[Host], list[str]]]:
    missing = hostsim.needs()
    assert not missing, f"simulated hosts need {missing}: scripts/bootstrap.sh installs them"
    with SimHosts(naming.unique_lab_name("h"), 2, tmp_path / "hosts") as hosts:
        labs = [naming.unique_lab_name("s"), naming.unique_lab_name("s")]
        addrs = [h.address for h in hosts.hosts]
        macs = ["02:5a:00:00:00:01", "02:5a:00:00:00:02"]
        started: list[Host] = []
        try:
            for i, host in enumerate(hosts.hosts):
                other = 1 - i
                cfg = {
                    "lab": labs[i],
                    "robot": f"r{i + 1}",
                    "mac": macs[i],
                    "address": f"10.99.0.{i + 1}/24",
                    "local": host.address,
                    "hosts": addrs,
                    "vni": 4242,
                    "remote": {f"r{other + 1}": macs[other]},
                }
                started.append(Host(hosts, host.alias, cfg))
            yield hosts, started, labs
        finally:
            for h in started:
                h.down()
    assert not [ns for ns in kernel.list_ns() if any(lab in ns for lab in labs)]


def ping(lab: str, robot: str, address: str) -> bool:
    argv = kernel.ns_argv(f"nl-{lab}-{robot}", ["ping", "-c", "2", "-i", "0.2", "-W", "1", address])
    return subprocess.run(argv, capture_output=True, check=False).returncode == 0


def test_robots_on_two_hosts_hear_each_other_and_the_receiver_judges_each_pair(
    two_hosts: tuple[SimHosts, list[Host], list[str]],
) -> None:
    _, (h1, h2), (lab1, _) = two_hosts
    both = [("r1", "r2"), ("r2", "r1")]
    assert not ping(lab1, "r1", "10.99.0.2")  # nothing loaded yet: the policy drops
    h1.load(both)
    h2.load(both)
    assert ping(lab1, "r1", "10.99.0.2")  # ARP's broadcast and the unicast crossed VXLAN
    h2.load([("r2", "r1")])  # the receiving host of r1's frames cuts r1 -> r2
    assert not ping(lab1, "r1", "10.99.0.2")
    h2.load(both)
    assert ping(lab1, "r1", "10.99.0.2")
