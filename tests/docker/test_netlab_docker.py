"""netlab's docker runtime: robots as containers of the robot image on a lab's medium.

The scenarios run through the `netlab` command as a user runs them; every test checks that
nothing of its lab is left afterwards: no container, namespace, manifest or veth.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from netlab import cleanup, docker, kernel, manifest, naming
from netlab.lab import Lab
from tests.docker.conftest import run
from tests.support.fleets import unique_lab_name
from tests.support.waiting import poll

pytestmark = pytest.mark.root


def netlab(*args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return run(sys.executable, "-m", "netlab.cli", *args, timeout=timeout)


def host_links() -> set[str]:
    """The root namespace's interfaces (a lab's veths never live here)."""
    out = run("ip", "-o", "link", "show").stdout
    return {line.split(":")[1].strip().split("@")[0] for line in out.splitlines()}


def volumes() -> set[str]:
    return set(run("docker", "volume", "ls", "-q").stdout.split())


def nothing_left(name: str) -> list[str]:
    left = cleanup.leftovers(name)  # namespaces, labelled containers, the manifest
    left += [f"container {c}" for c in docker.labelled(name)]
    return left


@pytest.fixture
def lab_name(image: str) -> Iterator[str]:
    """A unique lab name; the lab is taken down after the test whatever happened, and the
    test fails if anything of it, or a new veth in the root namespace or a volume, is left."""
    name = unique_lab_name()
    links, vols = host_links(), volumes()
    yield name
    netlab("down", name, "--cleanup")
    assert nothing_left(name) == []
    assert host_links() - links == set()
    assert volumes() - vols == set()


@pytest.mark.parametrize("scenario", ["partition-merge", "ip-collision"])
def test_bundled_scenario_passes_with_container_robots(
    lab_name: str, scenario: str, tmp_path: Path
) -> None:
    res = netlab(
        "run", scenario, "--runtime", "docker", "--lab", lab_name, "--runs", str(tmp_path)
    )  # fmt: skip
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-2000:]
    assert "robots (containers)" in res.stdout
    assert "PASSED" in res.stdout
    (folder,) = tmp_path.iterdir()
    meta = json.loads((folder / "run.json").read_text())["meta"]
    assert meta["runtime"] == "docker" and meta["status"] == "passed"
    # The daemons' logs (their containers' output) and captures made inside the containers'
    # namespaces are in the run folder as for namespace robots.
    assert "discovery up: robot r1" in (folder / "logs" / "r1.log").read_text()
    assert (folder / "r1.pcap").stat().st_size > 1000
    assert docker.labelled(lab_name) == []


def test_up_exec_status_down_with_containers(lab_name: str) -> None:
    up = netlab(
        "up", lab_name, "--robots", "3", "--runtime", "docker", "--start",
        "--beacon-interval", "0.5",
    )  # fmt: skip
    assert up.returncode == 0, up.stderr
    assert "3 robots (containers) up" in up.stdout
    containers = docker.labelled(lab_name)
    robot = f"nl-{lab_name}-r1"
    assert robot in containers and f"{robot}.sdfrd" in containers and len(containers) == 6

    def lists_the_others() -> bool | str:
        # `sdfr` of the robot image, run inside robot r1's container
        res = netlab("exec", lab_name, "r1", "--", "sdfr", "--json", "neighbors", timeout=60)
        if res.returncode != 0:
            return res.stderr
        seen = sorted(n["robot_id"] for n in json.loads(res.stdout)["neighbors"])
        return seen == ["r2", "r3"] or f"r1 lists {seen}"

    poll("r1 lists r2 and r3", lists_the_others, 30, step=0.5)
    inside = netlab("exec", lab_name, "r2", "--", "hostname")
    assert inside.stdout.strip() == "r2"  # the robot container's own filesystem and name
    status = json.loads(netlab("status", lab_name, "--json").stdout)["labs"][0]
    assert {r["runtime"] for r in status["robots"].values()} == {"docker"}
    assert all(r["present"] and r["sdfrd"] for r in status["robots"].values())
    down = netlab("down", lab_name, "--cleanup")
    assert down.returncode == 0, down.stderr
    assert "6 containers" in down.stdout and "4 namespaces" in down.stdout


def test_container_daemon_stops_kills_and_restarts_like_a_process(lab_name: str) -> None:
    with Lab(lab_name, runtime="docker") as lab:
        lab.add_robots(["a", "b"])
        lab.start_all(beacon_interval=0.5)
        sid = lab.client("a").publish("cam", "sensor.camera")
        pid = lab.daemon_pid("a")
        assert pid is not None
        # The daemon container's init is a host process in the robot's namespace.
        assert os.stat(f"/proc/{pid}/ns/net").st_ino == kernel.ns_inode(lab.robot("a").ns)[1]  # type: ignore[index]
        assert lab.stop("a") == 0  # SIGTERM: sdfrd says Byebye and exits 0
        assert "byebye sent" in lab.robot("a").log.read_text()
        lab.start("a", beacon_interval=0.5)
        assert [s["id"] for s in lab.client("a").services()] == [sid]  # the state dir kept it
        lab.kill("a")  # SIGKILL: a silent departure
        assert not lab.alive("a")
        state = docker.state(f"nl-{lab_name}-a.sdfrd")
        assert state is not None and not state.running and state.exit_code == 137
        lab.restart("a", beacon_interval=0.5)
        assert lab.alive("a")

        def b_lists_a_with_its_camera() -> bool | str:
            seen = {n["robot_id"]: n for n in lab.client("b").neighbors()}
            a = seen.get("a")
            ok = a is not None and a["reachable"] and [s["id"] for s in a["services"]] == [sid]
            return ok or f"b lists {seen}"

        # The robot's link, made once, outlived three runs of its daemon.
        poll("b lists a again, with its camera", b_lists_a_with_its_camera, 10)


def test_a_robot_that_fails_half_way_leaves_nothing_and_touches_no_one_elses(
    lab_name: str, image: str
) -> None:
    foreign = f"nl-{lab_name}-r2"  # a container of that name that is not the lab's
    made = run("docker", "run", "-d", "--name", foreign, "--network", "none",
               "--entrypoint", "sleep", image, "600")  # fmt: skip
    assert made.returncode == 0, made.stderr
    try:
        with Lab(lab_name, runtime="docker") as lab:
            lab.add_robot("r1")
            with pytest.raises(docker.DockerError, match=f"starting container {foreign}"):
                lab.add_robot("r2")
            assert list(lab.robots) == ["r1"]
            assert kernel.list_ns(naming.prefix(lab_name)) == sorted(
                [naming.air_ns(lab_name), f"nl-{lab_name}-r1"]
            )
            record = manifest.load(lab_name)
            assert record is not None and set(record.robots) == {"r1"}
            assert docker.labelled(lab_name) == [f"nl-{lab_name}-r1"]
        still = docker.state(foreign)
        assert still is not None and still.running
    finally:
        run("docker", "rm", "-f", "-v", foreign)


RUNNER = """
import sys
from netlab.lab import Lab
lab = Lab(sys.argv[1], runtime="docker").up()
print("up", flush=True)
lab.add_robots(["r1", "r2", "r3"])
lab.start_all(beacon_interval=0.5)
print("started", flush=True)
sys.stdin.read()
"""


@pytest.mark.parametrize("after", [0.4, 0.9, 1.4, 2.0])
def test_netlab_down_removes_a_container_lab_whose_runner_was_killed(
    lab_name: str, after: float
) -> None:
    """The runner dies at some point of making robots and starting daemons (a container made
    but not yet named as a namespace, a veth half-way, a daemon starting...): `netlab down`
    still removes everything, and says what."""
    runner = subprocess.Popen(
        [sys.executable, "-c", RUNNER, lab_name], stdin=subprocess.PIPE,
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert runner.stdout is not None
        assert runner.stdout.readline().strip() == "up"
        time.sleep(after)
        os.kill(runner.pid, signal.SIGKILL)
        runner.wait(10)
    finally:
        if runner.poll() is None:
            runner.kill()
            runner.wait()
    made = docker.labelled(lab_name)
    down = netlab("down", lab_name, "--cleanup")
    assert down.returncode == 0, down.stderr
    assert nothing_left(lab_name) == [], f"killed after {after} s with {made}"
    again = netlab("down", lab_name)
    assert again.returncode == 0 and "nothing to remove" in again.stdout


def test_a_topology_may_mix_kinds_and_be_partitioned_live(lab_name: str, tmp_path: Path) -> None:
    topo = tmp_path / "mixed.toml"
    topo.write_text(
        '[scenario]\nrobots = ["base", "scout"]\nbeacon = 0.5\n[kinds]\nbase = "docker"\n'
    )
    up = netlab("up", lab_name, "-t", str(topo), "--start")
    assert up.returncode == 0, up.stderr
    assert "2 robots (some containers) up" in up.stdout
    assert docker.labelled(lab_name) == [f"nl-{lab_name}-base", f"nl-{lab_name}-base.sdfrd"]

    def base_lists(expected: list[str]) -> bool | str:
        res = netlab("exec", lab_name, "base", "--", "sdfr", "--json", "neighbors", timeout=60)
        if res.returncode != 0:
            return res.stderr
        seen = sorted(n["robot_id"] for n in json.loads(res.stdout)["neighbors"] if n["reachable"])
        return seen == expected or f"base lists {seen}"

    poll("the container lists the namespace robot", lambda: base_lists(["scout"]), 20, step=0.5)
    assert netlab("partition", lab_name, "base", "scout").returncode == 0
    poll("the partition reaches the container", lambda: base_lists([]), 20, step=0.5)
    assert netlab("merge", lab_name).returncode == 0
    poll("and the merge", lambda: base_lists(["scout"]), 20, step=0.5)


def test_a_scenario_runs_with_container_robots_on_a_lab_across_hosts(
    image: str, tmp_path: Path
) -> None:
    """partition-merge with container robots spread over two simulated hosts (namespaces with
    their own sshd, reached over ssh): each host's agent runs its robots as containers of the
    robot image, joined to its share of the medium; the checks pass as on one host, and no
    container of any share is left."""
    from netlab import hostsim
    from netlab.hostsim import SimHosts

    missing = hostsim.needs()
    assert not missing, f"simulated hosts need {missing}: scripts/bootstrap.sh installs them"
    name = unique_lab_name()
    with SimHosts(naming.unique_lab_name("h"), 2, tmp_path / "hosts") as sim:
        res = netlab("run", "partition-merge", "--runtime", "docker", "--image", image,
                     "--lab", name, "--runs", str(tmp_path / "runs"), "--no-plots",
                     "--hosts", "h1,h2", "--ssh-config", str(sim.ssh_config),
                     "--host-python", sys.executable)  # fmt: skip
        out = res.stdout[-3000:] + res.stderr[-2000:]
        assert res.returncode == 0, out
        assert "6 robots on one medium across 2 hosts" in res.stdout, out
        assert "partition-merge: PASSED, 5 of 5 checks ok" in res.stdout, out
        (folder,) = (tmp_path / "runs").iterdir()
        meta = json.loads((folder / "run.json").read_text())["meta"]
        assert meta["runtime"] == "docker" and sorted(meta["hosts"]) == ["h1", "h2"]
        assert "discovery up: robot r1" in (folder / "logs" / "r1.log").read_text()
        shares = [f"{name[:7]}{i}" for i in range(2)]
        assert [c for s in shares for c in docker.labelled(s)] == []
        assert [ns for s in shares for ns in kernel.list_ns(naming.prefix(s))] == []
