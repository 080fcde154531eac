"""netlab.hosts against simulated hosts over real SSH: `look` (what `netlab doctor --hosts`
prints) passes hosts that can take part, with their clock offset, and names the reason of
one that cannot: unreachable (its sshd died), or another netlab version there."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from netlab import hosts, hostsim, naming
from netlab.hosts import Ssh
from netlab.hostsim import SimHosts
from sdfr import __version__

pytestmark = pytest.mark.root

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SimHosts]:
    missing = hostsim.needs()
    assert not missing, f"simulated hosts need {missing}: scripts/bootstrap.sh installs them"
    with SimHosts(naming.unique_lab_name("h"), 3, tmp_path_factory.mktemp("hosts")) as sim:
        yield sim


def ssh(sim: SimHosts, alias: str, python: str = sys.executable) -> Ssh:
    return Ssh(alias, sim.ssh_config, python, control_dir=sim.control_dir)


def test_hosts_that_can_take_part_pass_with_their_clock(sim: SimHosts) -> None:
    for alias in ("h1", "h2"):
        found = hosts.look(ssh(sim, alias))
        assert found.ok, found.problems
        assert found.version == __version__
        assert found.clock_offset is not None and found.clock_bound is not None
        assert abs(found.clock_offset) <= found.clock_bound + 0.01  # one machine, one clock
        assert found.line().startswith(f"{alias}: ok: netlab {__version__}, root, VXLAN, clock")


def test_a_host_with_another_version_or_no_netlab_is_named_with_the_reason(
    sim: SimHosts, tmp_path: Path
) -> None:
    other = tmp_path / "other" / "sdfr"
    other.mkdir(parents=True)
    (other / "__init__.py").write_text('__version__ = "9.9.9"\n')
    wrapper = tmp_path / "python-other"
    wrapper.write_text(f'#!/bin/sh\nPYTHONPATH={other.parent} exec {sys.executable} "$@"\n')
    wrapper.chmod(0o755)
    found = hosts.look(ssh(sim, "h2", str(wrapper)))
    assert not found.ok
    assert found.problems == (f"netlab 9.9.9 there, {__version__} here: run the same version "
                              "everywhere",)  # fmt: skip
    nothing = hosts.look(ssh(sim, "h2", "/usr/bin/python3"))  # the system's: no sdfr
    assert "no netlab for /usr/bin/python3 (ModuleNotFoundError" in nothing.problems[0]


def test_an_unreachable_host_fails_the_doctor_naming_it(sim: SimHosts) -> None:
    sim.kill_sshd("h3")
    found = hosts.look(ssh(sim, "h3"))
    assert found.problems == ("cannot be reached over ssh: ssh: connect to host "
                              f"{sim.hosts[2].address} port 22: Connection refused",)  # fmt: skip
    argv = [sys.executable, "-m", "netlab.cli", "doctor", "--hosts", "h1,h3",
            "--ssh-config", str(sim.ssh_config), "--host-python", sys.executable]  # fmt: skip
    done = subprocess.run(argv, capture_output=True, text=True, timeout=120, cwd=REPO)
    assert done.returncode == 1, done.stdout + done.stderr
    assert done.stdout.splitlines()[0].startswith("h1: ok: netlab")
    assert done.stdout.splitlines()[1].startswith("h3: cannot take part: cannot be reached")
    assert "1 of 2 hosts cannot take part: h3" in done.stderr
