"""Simulated hosts (netlab.hostsim): namespaces with their own underlay address and sshd, that
the controller reaches with plain ssh and its ssh_config, as it would real machines; a
host whose sshd died fails ssh with its reason; nothing is left behind."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from netlab import hostsim, naming
from netlab.hostsim import SimHosts

pytestmark = pytest.mark.root


@pytest.fixture(autouse=True)
def _needs() -> None:
    missing = hostsim.needs()
    assert not missing, f"simulated hosts need {missing}: scripts/bootstrap.sh installs them"


def ssh(hosts: SimHosts, alias: str, *argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        hosts.ssh_argv(alias, argv), capture_output=True, text=True, timeout=30, check=False
    )


def test_three_hosts_answer_over_ssh_each_in_its_namespace_and_reach_each_other(
    tmp_path: Path,
) -> None:
    name = naming.unique_lab_name("h")
    with SimHosts(name, 3, tmp_path / "hosts") as hosts:
        assert [h.alias for h in hosts.hosts] == ["h1", "h2", "h3"]
        for host in hosts.hosts:
            done = ssh(hosts, host.alias, "ip", "-4", "-br", "addr", "show", hostsim.UL_IFACE)
            assert done.returncode == 0, done.stderr
            assert f"{host.address}/24" in done.stdout  # its own namespace, its own address
            inode = ssh(hosts, host.alias, "readlink", "/proc/self/ns/net").stdout
            assert inode.strip() != os.readlink("/proc/self/ns/net")
        h2 = hosts.hosts[1].address
        done = ssh(hosts, "h1", "ping", "-c", "1", "-W", "2", h2)
        assert done.returncode == 0, done.stdout + done.stderr  # over the underlay
        hosts.kill_sshd("h3")
        dead = ssh(hosts, "h3", "true")
        assert dead.returncode == 255 and "Connection refused" in dead.stderr, dead.stderr
        made = [h.ns for h in hosts.hosts] + [hosts.underlay_ns]
    left = set(os.listdir("/run/netns")) & set(made) if os.path.isdir("/run/netns") else set()
    assert not left, f"namespaces left: {left}"
    links = subprocess.run(["ip", "-br", "link"], capture_output=True, text=True).stdout
    assert hosts.veth not in links
    sshd = subprocess.run(["pgrep", "-f", str(tmp_path / "hosts")], capture_output=True, text=True)
    assert sshd.stdout == "", f"sshd left: {sshd.stdout}"


def test_two_simulations_side_by_side_take_different_underlays(tmp_path: Path) -> None:
    a, b = naming.unique_lab_name("h"), naming.unique_lab_name("h")
    with SimHosts(a, 1, tmp_path / "a") as one, SimHosts(b, 1, tmp_path / "b") as two:
        assert not one.subnet.overlaps(two.subnet)
        assert ssh(one, "h1", "true").returncode == 0 and ssh(two, "h1", "true").returncode == 0


def test_a_bad_count_is_refused_saying_what_is_allowed(tmp_path: Path) -> None:
    with pytest.raises(Exception, match=r"1 to 200 hosts, got 0"):
        SimHosts(naming.unique_lab_name("h"), 0, tmp_path)
