"""The end-of-run leak check judges only what the run made: a session passes beside another
lab that stays up, and fails when one of its own tests leaves a namespace behind."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from netlab import hostlimits, kernel, manifest, naming
from netlab.lab import Lab

pytestmark = pytest.mark.root

REPO = Path(__file__).resolve().parents[2]

INNER = """
import subprocess

from netlab import naming
from netlab.lab import Lab


def test_a_lab_up_and_down(tmp_path):
    with Lab(naming.unique_lab_name("i"), workdir=tmp_path / "lab") as lab:
        lab.add_robot("r1")
        lab.add_robot("r2")


def test_maybe_leaks():
    if {leak!r}:
        subprocess.run(["ip", "netns", "add", {leaked!r}], check=True)
"""


def session(tmp_path: Path, *, leak: str | None) -> subprocess.CompletedProcess[str]:
    """A pytest session with the project's conftest, in a process of its own."""
    inner = tmp_path / "inner" / "test_inner.py"
    inner.parent.mkdir(parents=True)
    inner.write_text(INNER.format(leak=leak is not None, leaked=leak or ""))
    return subprocess.run(
        [
            *(sys.executable, "-m", "pytest", "-q", "-p", "tests.conftest"),
            *("-p", "no:cacheprovider", "--rootdir", str(inner.parent), str(inner)),
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
        stdin=subprocess.DEVNULL,
    )


def test_a_session_beside_another_lab_passes_and_a_real_leak_fails(
    lab_factory: Callable[..., Lab], tmp_path: Path
) -> None:
    # Another user's lab, up before the session and after it, big enough to raise the host's
    # ARP limits: its bookkeeping (.host.json) rightly stays while it is up.
    other = lab_factory()
    robots = hostlimits.max_mesh(hostlimits.current()["gc_thresh3"]) + 1
    if robots > 64:
        pytest.skip(f"the host's ARP limit already fits {robots - 1} robots: no lab raises it")
    with other.batch():
        for i in range(1, robots + 1):
            other.add_robot(f"r{i}")
    host = manifest.run_dir() / ".host.json"
    assert host.exists(), f"a lab of {robots} robots did not raise the ARP limits"

    ok = session(tmp_path / "a", leak=None)
    assert ok.returncode == 0, ok.stdout + ok.stderr
    assert "leaked resources" not in ok.stdout
    assert host.exists() and other.is_up  # the other lab's state is left alone

    leaked = f"{naming.NS_PREFIX}{naming.unique_lab_name('z')}-r1"
    bad = session(tmp_path / "b", leak=leaked)
    assert bad.returncode == 1, bad.stdout + bad.stderr
    assert f"network namespace {leaked} left behind" in bad.stdout
    assert "2 passed" in bad.stdout  # the tests passed; the session failed on the leak
    assert leaked not in kernel.list_ns(naming.NS_PREFIX)  # and it was removed
