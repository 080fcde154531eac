"""A lab across hosts, for real: three simulated hosts (namespaces with their own sshd,
reached over SSH like machines), each running its share of the lab through `netlab.agent`
(its robots with real sdfrd; the other hosts' robots known by MAC and position), the media
joined by VXLAN, driven by `netlab.spanlab.SpanLab`.  Six robots find each other across
hosts; a partition along the hosts cuts each side off within the bounds of one host; the
merge brings all back; a robot walking out of range is dropped on every host; a host that
cannot be reached at `down` is named while the others are cleaned up; a bundled scenario runs
on such a lab through the scenario engine, as it runs on one host."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import signal
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from netlab import cleanup, hostsim, kernel, manifest, naming, spankeep
from netlab.errors import NetlabError
from netlab.hosts import HostError, Ssh
from netlab.hostsim import SimHosts
from netlab.scenario import engine, files
from netlab.scenario.backend import LabLike, LabSpec
from netlab.spanlab import SpanLab, span_backend
from sdfr import __version__
from tests.support.netlab_cli import netlab

pytestmark = pytest.mark.root

REPO = Path(__file__).resolve().parents[2]
BEACON = 1.0
ROBOTS = {"r1": "h1", "r2": "h1", "r3": "h2", "r4": "h2", "r5": "h3", "r6": "h3"}


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[SimHosts]:
    missing = hostsim.needs()
    assert not missing, f"simulated hosts need {missing}: scripts/bootstrap.sh installs them"
    with SimHosts(naming.unique_lab_name("h"), 3, tmp_path / "hosts") as sim:
        yield sim


def hosts_of(sim: SimHosts) -> list[tuple[Ssh, str]]:
    return [(Ssh(h.alias, sim.ssh_config, sys.executable, control_dir=sim.control_dir), h.address)
            for h in sim.hosts]  # fmt: skip


def span_lab(sim: SimHosts, tmp_path: Path) -> SpanLab:
    hosts = hosts_of(sim)
    positions = {r: (2.0 * i, 0.0) for i, r in enumerate(ROBOTS)}
    return SpanLab(naming.unique_lab_name("x"), hosts, ROBOTS, positions_at_start=positions,
                   workdir=str(tmp_path / "parts"), env={"PYTHONPATH": str(REPO)})  # fmt: skip


def until(what: str, ok: Callable[[], bool], within: float) -> float:
    t0 = time.monotonic()
    while not ok():
        if time.monotonic() - t0 > within:
            raise AssertionError(f"not within {within:.1f} s: {what}")
        time.sleep(0.1)
    return time.monotonic() - t0


def lists(lab: SpanLab) -> dict[str, set[str]]:
    return {r: lab.neighbors(r) for r in ROBOTS}


def no_namespaces_of(lab: SpanLab) -> None:
    names = lab.part_names().values()
    left = [ns for ns in kernel.list_ns() if any(ns.startswith(naming.prefix(n)) for n in names)]
    assert not left, f"namespaces left: {left}"


def test_six_robots_on_three_hosts_find_each_other_split_along_the_hosts_merge_and_roam(
    sim: SimHosts, tmp_path: Path
) -> None:
    everyone = set(ROBOTS)
    sides = [["r1", "r2"], ["r3", "r4"], ["r5", "r6"]]
    with span_lab(sim, tmp_path) as lab:
        t0 = time.monotonic()
        lab.start_all(beacon_interval=BEACON)
        started = time.monotonic() - t0
        all_all = until(
            "every robot lists the five others, across hosts",
            lambda: all(v == everyone - {r} for r, v in lists(lab).items()),
            10 * BEACON,
        )
        lab.partition(sides)
        alone = {r: set(side) - {r} for side in sides for r in side}
        split = until(
            "each robot lists only its own host's other robot",
            lambda: lists(lab) == alone,
            3 * BEACON + 1.5,  # as on one host (docs/fleet-behaviour.md, row 5)
        )
        lab.merge()
        merged = until(
            "after the merge every robot lists the five others again",
            lambda: all(v == everyone - {r} for r, v in lists(lab).items()),
            BEACON + 2.0,
        )
        lab.move("r6", (500.0, 0.0))  # out of everyone's range, on every host's map
        away = {r: (everyone - {r, "r6"}) if r != "r6" else set() for r in ROBOTS}
        gone = until(
            "r6, walked out of range, is dropped by all and lists nobody",
            lambda: lists(lab) == away,
            3 * BEACON + 1.5,
        )
        # A daemon stopped on its host (SIGTERM within the timeout: exit 0, a Byebye) and
        # one killed there: the others drop each.
        assert lab.stop("r5", timeout=5.0) == 0
        rest = ["r1", "r2", "r3", "r4"]
        until("r5's Byebye is heard", lambda: all("r5" not in lab.neighbors(r) for r in rest), 2.0)
        lab.kill("r4")
        until("r4's silence is noticed", lambda: "r4" not in lab.neighbors("r1"), 3 * BEACON + 2)
        assert lab.daemons_ended() == {}  # (ended by the lab's own steps: not unexpected)
    no_namespaces_of(lab)
    print(f"\nacross 3 hosts: healthy in {started:.2f} s, all list all {all_all:.2f} s later; "
          f"split seen in {split:.2f} s; merged in {merged:.2f} s; out of range dropped in "
          f"{gone:.2f} s (beacon {BEACON:.0f} s)")  # fmt: skip


def test_a_host_lost_before_down_is_named_and_the_others_are_cleaned_up(
    sim: SimHosts, tmp_path: Path
) -> None:
    lab = span_lab(sim, tmp_path)
    lost = r"host h3: down: (its agent ended|cannot be reached)"
    with pytest.raises(HostError, match=lost), lab:
        lab.start_all(beacon_interval=BEACON)
        # h3 dies: its sshd and every process of its sessions (its agent) go at once.
        sim.kill_sshd("h3")
        inode = kernel.ns_inode(sim.hosts[2].ns)
        assert inode is not None
        killed = cleanup.kill_inside({inode})
        assert killed, "no process of h3's session was found"
    names = lab.part_names()
    left = [ns for ns in kernel.list_ns() if ns.startswith(naming.prefix(names["h3"]))]
    assert left, "h3's share was not left behind (nothing to find after a host is lost)"
    for other in ("h1", "h2"):
        assert not [ns for ns in kernel.list_ns() if ns.startswith(naming.prefix(names[other]))]
    # What a lost host leaves is swept by `netlab down` there, as after any crash.
    try:
        cleanup.sweep(names["h3"], manifest.load(names["h3"]))
        manifest.remove(names["h3"])
    except NetlabError as exc:
        pytest.fail(f"the sweep of h3's share failed: {exc}")
    no_namespaces_of(lab)


def test_partition_merge_runs_with_netlab_run_across_the_hosts_its_file_names(
    sim: SimHosts, tmp_path: Path
) -> None:
    """The bundled partition-merge with a [hosts] table (two robots placed, the rest spread),
    run by `netlab run` over ssh: the same checks pass within the same deadlines as on one
    host, the one that counts in captures too (tcpdumps on every host, their pcaps fetched
    and merged on this clock); each robot's log is fetched from its host."""
    text = (files.BUNDLED_DIR / "partition-merge.toml").read_text()
    placed = '\n[hosts]\nh1 = ["r1", "r6"]\nh2 = []\nh3 = []\n'
    (tmp_path / "pm.toml").write_text(text.replace("\n[[step]]", placed + "\n[[step]]", 1))
    run_dir = tmp_path / "runs"
    done = netlab("run", str(tmp_path / "pm.toml"), "--runs", str(run_dir), "--no-plots",
                  "--ssh-config", str(sim.ssh_config), "--host-python", sys.executable,
                  timeout=300)  # fmt: skip
    out = done.stdout + done.stderr
    assert done.returncode == 0, out
    assert "6 robots on one medium across 3 hosts (clocks within" in out
    assert "capturing on every host (9 tcpdumps" in out  # 3 media, 6 robots
    assert "partition-merge: PASSED, 5 of 5 checks ok" in out
    [folder] = run_dir.iterdir()
    meta = json.loads((folder / "report.json").read_text())["meta"]
    assert len(meta["checks"]) == 5 and all(c["ok"] for c in meta["checks"]), out
    assert_one_medium_of_every_frame(folder)
    hosts = meta["hosts"]
    assert sorted(hosts) == ["h1", "h2", "h3"] and hosts["h1"]["robots"] == ["r1", "r6"]
    for h in hosts.values():  # one machine's clock: the offset is within its bound, < 50 ms
        assert abs(h["clock_offset_s"]) <= h["clock_bound_s"] + 1e-3 < 0.05, hosts
    where = {}  # each robot's host's share, from the first line of its log (its command)
    for robot in [f"r{i}" for i in range(1, 7)]:
        first = (folder / "logs" / f"{robot}.log").read_text().splitlines()[0]
        assert f"--robot-id {robot} " in first, first
        where[robot] = re.search(r"--state-dir \S*/netlab-(\w+?)-", first)
    shares = {r: m.group(1) if m else None for r, m in where.items()}
    assert shares["r1"] == shares["r6"] and shares["r1"] is not None, shares
    others = [shares[r] for r in ("r2", "r3", "r4", "r5")]
    assert shares["r1"] not in others and sorted(set(others)) == sorted(set(others) - {None})
    assert len(set(others)) == 2 and others.count(others[0]) == 2, shares  # spread 2 and 2
    print("\n" + out)


def test_mobility_across_three_hosts_agrees_with_the_medium(sim: SimHosts, tmp_path: Path) -> None:
    """Robots walking while their hosts' media follow every move: the bundled mobility
    scenario's agreement checks hold across hosts as on one (its quick walk)."""
    made: list[SpanLab] = []
    backend = span_backend(hosts_of(sim), env={"PYTHONPATH": str(REPO)})

    def make(spec: LabSpec) -> LabLike:
        lab = backend.make_lab(spec)
        assert isinstance(lab, SpanLab)
        made.append(lab)
        return lab

    said: list[str] = []
    sc = files.load(files.bundled()["mobility"])
    res = engine.run(sc, lab_name=naming.unique_lab_name("x"), run_dir=tmp_path / "run",
                     backend=dataclasses.replace(backend, make_lab=make), say=said.append,
                     quick=True, plots=False)  # fmt: skip
    log = "\n".join(said)
    assert res.status == "passed", log
    [lab] = made
    assert sorted(lab.placed.values()) == ["h1", "h1", "h2", "h2", "h3", "h3"]
    judged = [c for c in res.checks if c.kind != "updates"]
    assert judged and all(c.ok for c in judged), log
    no_namespaces_of(lab)
    print("\n" + log)


def test_a_host_with_another_netlab_version_is_named_before_anything_is_made(
    sim: SimHosts, tmp_path: Path
) -> None:
    """h2 runs another release (a copy of this one with another version): `up` names the
    host and both versions, and no host has made any of the lab."""
    other = tmp_path / "other"
    for package in ("sdfr", "netlab"):
        shutil.copytree(REPO / package, other / package,
                        ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    init = other / "sdfr" / "__init__.py"
    init.write_text(re.sub(r'__version__ = "[^"]*"', '__version__ = "9.9.9"', init.read_text()))
    hosts = hosts_of(sim)
    hosts[1] = (dataclasses.replace(hosts[1][0], python=str(wrapper(tmp_path, other))), None)
    lab = SpanLab(naming.unique_lab_name("x"), hosts, ROBOTS, env={"PYTHONPATH": str(REPO)})
    with pytest.raises(HostError) as refused, lab:
        pass
    assert str(refused.value) == (
        f"host h2: netlab 9.9.9 there, {__version__} here: run the same version on every host"
    )
    no_namespaces_of(lab)
    assert not lab.placed


def wrapper(tmp_path: Path, path: Path) -> Path:
    """An interpreter that imports from `path` first (an agent's env would set it after)."""
    exe = tmp_path / "python-other"
    exe.write_text(f'#!/bin/sh\nexport PYTHONPATH={path}\nexec {sys.executable} "$@"\n')
    exe.chmod(0o755)
    return exe


def assert_one_medium_of_every_frame(folder: Path) -> None:
    """medium.pcap, merged from the hosts' media, has each frame a robot sent once: the
    datagrams in it are those the robots' own captures saw them send, no more, in time order."""
    from netlab.pcap import read_pcap

    medium = [r for r in read_pcap(folder / "medium.pcap") if r.kind == "sdfr"]
    times = [r.time for r in medium]
    assert times == sorted(times)
    sent = {}
    for robot in [f"r{i}" for i in range(1, 7)]:
        own = read_pcap(folder / f"{robot}.pcap")
        sent[robot] = sum(1 for r in own if r.kind == "sdfr" and r.direction == "tx")
    seen = {robot: sum(1 for r in medium if r.robot == robot) for robot in sent}
    # A frame sent in the last instant before the captures stopped may be in one, not the other.
    assert all(abs(seen[r] - sent[r]) <= 2 for r in sent), (seen, sent)
    assert all(n > 10 for n in sent.values()), sent


def shares_left(shares: list[str]) -> list[str]:
    return [ns for ns in kernel.list_ns() if any(ns.startswith(naming.prefix(s)) for s in shares)]


def test_up_status_partition_shape_merge_down_across_hosts_from_the_command_line(
    sim: SimHosts,
) -> None:
    """`netlab up --hosts` leaves a keeper holding the lab; status, partition, shape and merge
    go through it; exec names the robot's host; down takes every host's share down."""
    name = naming.unique_lab_name("u")
    ssh = ["--ssh-config", str(sim.ssh_config), "--host-python", sys.executable]
    up = netlab("up", name, "--robots", "6", "--spacing", "2", "--hosts", "h1,h2,h3", *ssh,
                "--start", "--beacon-interval", "1", timeout=300)  # fmt: skip
    try:
        out = up.stdout + up.stderr
        assert up.returncode == 0, out
        assert "6 robots on one medium across 3 hosts" in out, out
        assert "sdfrd runs on all 6 robots, healthy in" in out, out
        record = spankeep.load(name)
        assert record is not None and record.keeper_alive()
        assert record.robots == {"r1": "h1", "r2": "h2", "r3": "h3",
                                 "r4": "h1", "r5": "h2", "r6": "h3"}  # fmt: skip
        status = netlab("status", name, "--json")
        assert status.returncode == 0, status.stderr
        span = json.loads(status.stdout)["across_hosts"][name]
        assert span["linked_pairs"] == 15 and span["robots"] == 6, span
        assert all(h["session"] == "up" and len(h["robots"]) == 2 for h in span["hosts"].values())
        text = netlab("status").stdout
        assert f"lab {name}: 6 robots on one medium across 3 hosts" in text, text
        assert f"host h2: share {record.shares['h2']} (up): r2, r5" in text, text

        assert span["daemons_ended"] == {}, span  # (healthy at start: up said so)

        # A robot is reached in its host's share, there (one machine here: the shares' too).
        there = netlab("exec", record.shares["h3"], "r3", "--", "ip", "-o", "link", "show")
        assert there.returncode == 0 and "eth0" in there.stdout, there.stderr
        wrong = netlab("exec", name, "r3", "--", "true")
        assert wrong.returncode == 1
        assert f"r3 is on h3, in its share {record.shares['h3']} there" in wrong.stderr

        part = netlab("partition", name, "r1,r2", "r3,r4,r5,r6")
        assert part.returncode == 0, part.stderr
        assert "7 linked pairs across its hosts" in part.stdout, part.stdout  # 1 + 6
        bad = netlab("partition", name, "r1,r9")
        assert bad.returncode == 1 and "no robot 'r9'" in bad.stderr, bad.stderr
        shaped = netlab("shape", name, "r4", "--rate", "1mbit")
        assert shaped.returncode == 0 and "r4:" in shaped.stdout, shaped.stderr
        merged = netlab("merge", name)
        assert "merged; 15 linked pairs" in merged.stdout, merged.stdout + merged.stderr
    finally:
        down = netlab("down", name, timeout=120)
    assert down.returncode == 0, down.stdout + down.stderr
    assert f"lab {name} removed from 3 hosts" in down.stdout
    kept = re.findall(r"share \w+ down, kept its folder (\S+)", down.stdout)
    assert len(kept) == 3, down.stdout  # (as on one host: the daemon logs stay)
    for folder in kept:
        assert list(Path(folder).glob("r*/sdfrd.log")), folder
        shutil.rmtree(folder)
    assert spankeep.load(name) is None and not spankeep.log_path(name).exists()
    assert not shares_left(list(record.shares.values()))
    assert not record.keeper_alive()


def test_a_lab_whose_keeper_was_killed_is_gone_from_every_host_and_down_says_so(
    sim: SimHosts, tmp_path: Path
) -> None:
    """A topology file's [hosts] spreads `netlab up`'s lab (r3 placed on h1).  Kill -9 the
    keeper: the hosts take their shares down as its sessions end; status says the keeper is
    gone; down asks each host and removes the record."""
    name = naming.unique_lab_name("k")
    ssh = ["--ssh-config", str(sim.ssh_config), "--host-python", sys.executable]
    topology = tmp_path / "three.toml"
    topology.write_text('[scenario]\nname = "three"\nrobots = 3\n\n[hosts]\nh1 = ["r3"]\nh2 = []\n')
    up = netlab("up", name, "-t", str(topology), *ssh, timeout=300)
    assert up.returncode == 0, up.stdout + up.stderr
    assert "sdfrd runs on no robot" in up.stdout
    record = spankeep.load(name)
    assert record is not None
    assert record.robots == {"r1": "h2", "r2": "h1", "r3": "h1"}, record.robots
    shares = list(record.shares.values())
    assert len(shares_left(shares)) >= 3  # each robot's namespace, at least
    os.kill(record.pid, signal.SIGKILL)
    until("every host took its share down", lambda: not shares_left(shares), 30.0)
    status = netlab("status", name)
    assert status.returncode == 1 and "its keeper (pid" in status.stderr, status.stderr
    listing = netlab("status")  # every lab: this one's trouble said, the others listed
    assert listing.returncode == 0 and f"lab {name} (across hosts): " in listing.stdout
    down = netlab("down", name)
    assert down.returncode == 0, down.stdout + down.stderr
    assert "was gone: asking each host" in down.stdout
    assert spankeep.load(name) is None and not spankeep.log_path(name).exists()

    # A host that cannot be reached: up says which, and nothing is left anywhere.
    failed = netlab("up", name, "--robots", "2", "--hosts", "h1,nosuch.invalid", *ssh)
    assert failed.returncode == 1, failed.stdout + failed.stderr
    assert "host nosuch.invalid: hello: cannot be reached over ssh" in failed.stderr
    assert spankeep.load(name) is None and not spankeep.socket_path(name).exists()
    assert not shares_left([f"{name[:7]}{i}" for i in range(2)])
    assert not spankeep.log_path(name).exists()  # (its error said it all)


def test_silent_departure_and_ip_collision_pass_across_three_hosts(
    sim: SimHosts, tmp_path: Path
) -> None:
    """Two more bundled scenarios, spread over the three hosts by `netlab run --hosts`: a
    robot killed with kill -9 and a link cut, each noticed and back, within the deadlines they
    have on one host; and sdfrd's own addresses (`addressing = "auto"`), two robots deriving
    the same one on different hosts, the conflict found and settled across the VXLAN."""
    for name in ("silent-departure", "ip-collision"):
        done = netlab("run", name, "--runs", str(tmp_path / name), "--no-plots",
                      "--hosts", "h1,h2,h3", "--ssh-config", str(sim.ssh_config),
                      "--host-python", sys.executable, timeout=300)  # fmt: skip
        out = done.stdout + done.stderr
        assert done.returncode == 0, out
        assert "on one medium across 3 hosts" in out, out
        assert re.search(rf"{name}: PASSED, (\d+) of \1 checks ok", out), out
