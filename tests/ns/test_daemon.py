"""Real `sdfrd` daemons in network namespaces on one bridge (needs root)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from netlab.lab import Lab
from sdfr.client import Client
from sdfr.config import keystore
from sdfr.daemon import MALLOC_TUNABLES
from sdfr.daemon.supervisor import LOCK_NAME, lock_state_dir
from tests.support.waiting import poll

pytestmark = pytest.mark.root

BEACON = 1.0


class Robots:
    """Daemons in a netlab lab; robot i runs sdfrd with its state in tmp/ri."""

    def __init__(self, lab: Lab, tmp: Path) -> None:
        self.lab = lab
        self.tmp = tmp
        self.procs: dict[int, subprocess.Popen[Any]] = {}
        self.clients: dict[int, Client] = {}

    def state(self, i: int) -> Path:
        return self.tmp / f"r{i}"

    def start(self, i: int, *extra: str) -> None:
        name = f"r{i}"
        argv = self.lab.sdfrd_argv(name, state_dir=self.state(i), beacon_interval=BEACON)
        with open(self.tmp / f"r{i}.log", "ab") as out:
            self.procs[i] = self.lab.popen(
                name, [*argv, *extra], stdout=out, stderr=subprocess.STDOUT
            )
        self.wait_healthy(i)

    def exec(self, i: int, argv: list[str]) -> subprocess.CompletedProcess[str]:
        return self.lab.exec(f"r{i}", argv)

    def kill(self, proc: subprocess.Popen[Any], sig: int = signal.SIGTERM) -> None:
        """Signal the daemon's whole process group (it runs in a session of its own)."""
        if proc.poll() is None:
            os.killpg(proc.pid, sig)

    def client(self, i: int) -> Client:
        if i not in self.clients:
            self.clients[i] = Client(unix_socket=self.state(i) / "api.sock", timeout=2.0)
        return self.clients[i]

    def wait_healthy(self, i: int, timeout: float = 15.0) -> None:
        poll(
            f"r{i} healthy",
            lambda: self.client(i).health().get("discovery") == "up",
            timeout,
        )

    def layers(self, i: int) -> dict[str, int]:
        return dict(json.loads((self.state(i) / "layers.json").read_text()))

    def reachable(self, i: int) -> set[str]:
        return {n["robot_id"] for n in self.client(i).neighbors()}

    def services_of(self, i: int, robot: str) -> set[str]:
        for n in self.client(i).neighbors():
            if n["robot_id"] == robot:
                return {s["name"] for s in n["services"]}
        return set()

    def history(self, i: int) -> dict[str, dict[str, Any]]:
        return {r["robot_id"]: r for r in self.client(i).history()}

    def log(self, i: int) -> str:
        return (self.tmp / f"r{i}.log").read_text(errors="replace")

    def close(self) -> None:
        for c in self.clients.values():
            c.close()


@pytest.fixture
def robots(fleet_factory: Callable[..., Lab], tmp_path: Path) -> Iterator[Robots]:
    r = Robots(fleet_factory(3, start=False), tmp_path)
    try:
        yield r
    finally:
        r.close()


def all_see_all(r: Robots, ids: list[int]) -> bool:
    return all(r.reachable(i) >= {f"r{j}" for j in ids if j != i} for i in ids)


def test_three_daemons_discover_publish_leave_die_and_restore(robots: Robots) -> None:
    r = robots
    for i in (1, 2, 3):
        r.start(i)
    poll("all see all", lambda: all_see_all(r, [1, 2, 3]), 5.0)

    # A service published on r1 is listed by r2 and r3 within 1 s.
    sid = r.client(1).publish("front camera", "sensor.camera", attributes={"fps": 30})
    took = poll(
        "camera on r2 and r3",
        lambda: all("front camera" in r.services_of(j, "r1") for j in (2, 3)),
        1.0,
    )
    assert took < 1.0
    found = r.client(3).search("sensor.camera", fps=30)
    assert [n["robot_id"] for n in found] == ["r1"]
    r.client(1).unpublish(sid)
    poll("unpublish seen", lambda: "front camera" not in r.services_of(2, "r1"), 1.0)

    # Byebye: a graceful stop removes r3 from the reachable lists at once; history keeps it.
    r.client(3).publish("lidar", "sensor.lidar")
    poll("lidar seen", lambda: "lidar" in r.services_of(1, "r3"), 1.0)
    r.kill(r.procs[3], signal.SIGTERM)
    took = poll("r3 gone", lambda: all("r3" not in r.reachable(j) for j in (1, 2)), 1.0)
    assert took < 0.5
    assert r.procs[3].wait(5) == 0
    hist = r.history(1)["r3"]
    assert hist["reachable"] is False and [s["name"] for s in hist["services"]] == ["lidar"]

    # Restarted on the same state dir: its registration is back, and so is it.
    r.start(3)
    assert [s["name"] for s in r.client(3).services()] == ["lidar"]
    poll("r3 back with lidar", lambda: all("lidar" in r.services_of(j, "r3") for j in (1, 2)), 3.0)

    # kill -9: a silent death. Unreachable within 3 beacon periods, still in history.
    r.client(2).publish("arm", "actuator.arm", attributes={"dof": 6})
    poll("arm seen", lambda: "arm" in r.services_of(1, "r2"), 1.0)
    before = r.history(1)["r2"]["indicator"]
    r.kill(r.procs[2], signal.SIGKILL)
    r.procs[2].wait(5)
    took = poll(
        "r2 unreachable", lambda: all("r2" not in r.reachable(j) for j in (1, 3)), 3 * BEACON + 0.5
    )
    assert took <= 3 * BEACON + 0.3
    hist = r.history(1)["r2"]
    assert hist["reachable"] is False and [s["name"] for s in hist["services"]] == ["arm"]
    assert before is None or hist["indicator"] is None or hist["indicator"] <= before

    # The whole daemon restarted with the same state dir restores its registrations.
    r.start(2)
    assert [s["name"] for s in r.client(2).services()] == ["arm"]
    poll("r2 back with arm", lambda: all("arm" in r.services_of(j, "r2") for j in (1, 3)), 3.0)


def test_one_daemon_per_state_dir(robots: Robots) -> None:
    r = robots
    r.start(1)
    state = r.state(1)
    pids = r.layers(1)
    # Both layers hold the lock too (inherited), so it outlives a supervisor that dies first.
    lock = (state / LOCK_NAME).resolve()
    for layer in ("api", "discovery"):
        fds = Path(f"/proc/{pids[layer]}/fd")
        assert any(fd.readlink() == lock for fd in fds.iterdir()), layer
    # A second daemon on the same state dir (from another robot's namespace, with a key
    # file it would seed the keyring from) is refused before it touches anything.
    key = r.tmp / "fleet.key"
    keystore.generate_key_file(key)
    res = r.exec(
        2,
        [
            sys.executable, "-m", "sdfr.daemon.supervisor", "--iface", "eth0",
            "--robot-id", "r9", "--state-dir", str(state), "--key-file", str(key),
        ],
    )  # fmt: skip
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip() == (
        f"sdfrd: state_dir {state} is in use by another sdfrd (pid {pids['supervisor']}); "
        "give each daemon its own --state-dir"
    )
    assert not keystore.keyring_path(state).exists()
    assert r.layers(1) == pids
    assert r.client(1).health()["discovery"] == "up"
    # Stopped, the daemon leaves the state dir free for the next one.
    r.kill(r.procs[1])
    assert r.procs[1].wait(timeout=10) == 0
    os.close(lock_state_dir(state))


def test_sdfrd_runs_with_glibc_malloc_pinned(robots: Robots) -> None:
    """netlab starts the `sdfrd` entry point, which re-execs itself once (same pid) with
    malloc's mmap threshold pinned: without it every heap keeps ~0.5 MiB it freed."""
    if any(k == "GLIBC_TUNABLES" or k.startswith("MALLOC_") for k in os.environ):
        pytest.skip("this environment sets malloc tunables itself; sdfrd leaves them alone")
    robots.start(1)
    pid = robots.layers(1)["supervisor"]
    environ = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    assert f"GLIBC_TUNABLES={MALLOC_TUNABLES}".encode() in environ
    assert robots.procs[1].poll() is None


def test_layers_have_independent_life_cycles(robots: Robots) -> None:
    r = robots
    r.start(1, "--layers", "processes")  # (threads: tests/ns/test_supervision.py)
    r.start(2)
    poll("r1 and r2 see each other", lambda: all_see_all(r, [1, 2]), 5.0)
    r.client(1).publish("mapper", "slam.map")
    poll("mapper seen", lambda: "mapper" in r.services_of(2, "r1"), 1.0)

    # Kill the discovery layer: the API still answers from the last known state and
    # says discovery is down; the supervisor brings it back. (The supervisor forks a new
    # layer 0.2 s after the old one died: it is held stopped meanwhile, so that "down" is
    # seen for as long as the checks take, not for a window a busy machine can miss.)
    pids = r.layers(1)
    disc = pids["discovery"]
    os.kill(pids["supervisor"], signal.SIGSTOP)
    try:
        os.kill(disc, signal.SIGKILL)
        poll("health degraded", lambda: r.client(1).health().get("discovery") == "down", 3.0)
        assert "r2" in {n["robot_id"] for n in r.client(1).neighbors(include_unreachable=True)}
        assert [s["name"] for s in r.client(1).services()] == ["mapper"]
        sid = r.client(1).publish("planner", "nav.plan")  # accepted while discovery is down
    finally:
        os.kill(pids["supervisor"], signal.SIGCONT)
    poll("discovery restarted", lambda: r.layers(1).get("discovery", disc) != disc, 5.0)
    r.wait_healthy(1)
    poll("planner announced", lambda: "planner" in r.services_of(2, "r1"), 3.0)

    # Kill the API layer: discovery keeps running (r2 keeps r1 reachable), the API returns.
    api = r.layers(1)["api"]
    os.kill(api, signal.SIGKILL)
    time.sleep(3 * BEACON + 0.5)
    assert "r1" in r.reachable(2)
    poll("api restarted", lambda: r.layers(1).get("api", api) != api, 5.0)
    r.client(1).close()
    r.wait_healthy(1)
    r.client(1).unpublish(sid)
    poll("planner gone", lambda: "planner" not in r.services_of(2, "r1"), 1.0)


def test_standard_ssdp_client_and_location(robots: Robots) -> None:
    r = robots
    for i in (1, 2, 3):
        r.start(i)
    poll("all see all", lambda: all_see_all(r, [1, 2, 3]), 5.0)
    r.client(2).publish("gripper", "actuator.gripper")
    # A plain SSDP M-SEARCH ssdp:all from r1's namespace (an ephemeral port, like any
    # UPnP control point) gets a unicast 200 OK from every robot, r1's own included.
    script = r"""
import socket, time, json, urllib.request
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("10.1.0.1"))
s.sendto(b'M-SEARCH * HTTP/1.1\r\nHOST: 239.255.255.250:1900\r\nMAN: "ssdp:discover"\r\n'
         b'MX: 1\r\nST: ssdp:all\r\n\r\n', ("239.255.255.250", 1900))
s.settimeout(0.2)
found = {}
end = time.time() + 2.0
while time.time() < end:
    try:
        data, addr = s.recvfrom(2048)
    except socket.timeout:
        continue
    head = dict(l.split(": ", 1) for l in data.decode().split("\r\n")[1:] if ": " in l)
    found[addr[0]] = (data.split(b"\r\n")[0].decode(), head.get("LOCATION"), head.get("USN"))
out = {}
for ip, (line, loc, usn) in found.items():
    desc = json.load(urllib.request.urlopen(loc, timeout=2))
    out[ip] = {"line": line, "usn": usn, "robot": desc["robot_id"],
               "services": [s["name"] for s in desc["services"]]}
print(json.dumps(out))
"""
    res = r.exec(1, [sys.executable, "-c", script])
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    assert sorted(out) == ["10.1.0.1", "10.1.0.2", "10.1.0.3"]
    assert {v["line"] for v in out.values()} == {"HTTP/1.1 200 OK"}
    assert out["10.1.0.2"]["robot"] == "r2" and out["10.1.0.2"]["services"] == ["gripper"]
    assert out["10.1.0.2"]["usn"].startswith("uuid:r2")
    # The write API is not reachable from another robot.
    res = r.exec(
        1,
        [sys.executable, "-c", "import socket; socket.create_connection(('10.1.0.2', 8700), 1)"],
    )
    assert res.returncode != 0


def test_cli_in_namespace_and_bad_flags(robots: Robots) -> None:
    r = robots
    r.start(1)
    r.start(2)
    poll("r1 and r2 see each other", lambda: all_see_all(r, [1, 2]), 5.0)
    sdfr = [sys.executable, "-m", "sdfr.cli"]
    res = r.exec(1, [*sdfr, "publish", "cam", "sensor.camera", "--attr", "fps=30"])
    assert res.returncode == 0, res.stderr
    poll("cam seen", lambda: "cam" in r.services_of(2, "r1"), 1.0)
    res = r.exec(2, [*sdfr, "--json", "neighbors"])
    assert res.returncode == 0, res.stderr
    names = [n["robot_id"] for n in json.loads(res.stdout)["neighbors"]]
    assert names == ["r1"]
    res = r.exec(2, [*sdfr, "neighbors"])
    assert "r1" in res.stdout and "10.1.0.1" in res.stdout
    # A daemon given a bad flag says what is wrong and exits 2, without a traceback.
    res = r.exec(
        3,
        [
            sys.executable,
            "-m",
            "sdfr.daemon.supervisor",
            "--iface",
            "nope0",
            "--state-dir",
            str(r.tmp / "bad"),
        ],
    )
    assert res.returncode == 2 and "iface" in res.stderr and "Traceback" not in res.stderr
    res = r.exec(3, [sys.executable, "-m", "sdfr.daemon.supervisor", "--fleet", "300"])
    assert res.returncode == 2 and "fleet" in res.stderr and "Traceback" not in res.stderr
