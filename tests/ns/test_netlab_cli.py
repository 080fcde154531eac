"""`netlab` on real labs: down keeps the folder, logs, exec --all, pingall, status's medium, and
a failed test's daemon logs kept where its report says."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.support.netlab_cli import cli_lab, netlab

pytestmark = pytest.mark.root

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def name() -> Iterator[str]:
    yield from cli_lab()


def _folder(up: subprocess.CompletedProcess[str]) -> Path:
    line = next(li for li in up.stdout.splitlines() if li.startswith("folder "))
    return Path(line.split()[1])


def test_down_keeps_the_folder_with_the_daemon_logs_unless_cleanup(name: str) -> None:
    up = netlab("up", name, "--robots", "2", "--start", "--beacon-interval", "0.5")
    assert up.returncode == 0, up.stderr
    assert "sdfrd runs on all 2 robots" in up.stdout
    folder = _folder(up)
    down = netlab("down", name)
    assert down.returncode == 0, down.stderr
    assert f"kept its folder {folder}" in down.stdout and f"rm -r {folder}" in down.stdout
    try:
        assert (folder / "r1" / "sdfrd.log").stat().st_size > 0
        logs = netlab("logs", str(folder), "r1")  # read after the lab is gone
        assert logs.returncode == 0 and "sdfrd" in logs.stdout, logs.stderr
    finally:
        shutil.rmtree(folder, ignore_errors=True)

    up = netlab("up", name, "--robots", "1")
    assert up.returncode == 0, up.stderr
    assert "sdfrd runs on no robot: `netlab up ... --start`" in up.stdout
    folder = _folder(up)
    down = netlab("down", name, "--cleanup")
    assert down.returncode == 0 and f"folder {folder}" in down.stdout
    assert not folder.exists()


def test_logs_prints_and_follows_a_robots_daemon_log(name: str) -> None:
    up = netlab("up", name, "--robots", "2", "--start", "--beacon-interval", "0.5")
    assert up.returncode == 0, up.stderr
    log = _folder(up) / "r2" / "sdfrd.log"
    whole = netlab("logs", name, "r2")
    assert whole.returncode == 0 and whole.stdout.startswith(log.read_text()[:40])
    assert netlab("logs", name, "r2", "-n", "1").stdout.count("\n") == 1
    wrong = netlab("logs", name, "r3")
    assert wrong.returncode == 1 and "no robot 'r3'" in wrong.stderr
    follow = subprocess.Popen(
        [sys.executable, "-m", "netlab.cli", "logs", name, "r2", "-f", "-n", "1"],
        stdout=subprocess.PIPE, text=True, stdin=subprocess.DEVNULL,
    )  # fmt: skip
    guard = threading.Timer(30.0, follow.kill)  # a line that never comes fails, not hangs
    guard.start()
    try:
        assert follow.stdout is not None
        assert follow.stdout.readline()  # the last line: it follows from here on
        with open(log, "a") as f:
            f.write("a line appended while following\n")
        line = follow.stdout.readline()
        while line and "appended while following" not in line:
            line = follow.stdout.readline()
        assert "appended while following" in line
    finally:
        guard.cancel()
        follow.send_signal(signal.SIGINT)
        assert follow.wait(10) == 130


def test_exec_all_runs_in_every_robot_with_its_name_and_the_worst_status(name: str) -> None:
    assert netlab("up", name, "--robots", "3").returncode == 0
    script = (
        "ip -o -4 addr show eth0 | grep -o '10[.0-9]*/16'; "
        "ip -o addr | grep -q 10.1.0.2/ && exit 3; exit 0"
    )
    out = netlab("exec", "--all", name, "--", "sh", "-c", script)
    assert out.returncode == 3, out.stderr
    lines = sorted(out.stdout.splitlines())
    assert lines == ["r1 | 10.1.0.1/16", "r2 | 10.1.0.2/16", "r3 | 10.1.0.3/16"]
    assert "exit status r2 3 of 3 robots" in out.stderr
    assert netlab("exec", name, "--all", "--", "true").returncode == 0


def test_pingall_matrix_follows_the_medium_and_fails_a_silent_linked_pair(name: str) -> None:
    assert netlab("up", name, "--robots", "3").returncode == 0
    assert netlab("partition", name, "r1").returncode == 0
    status = netlab("status", name)
    assert "medium: partition r1 | r2,r3;" in status.stdout and "2 of 6 directed" in status.stdout
    ok = netlab("pingall", name, "--count", "2")
    assert ok.returncode == 0, ok.stdout + ok.stderr
    rows = {li.split()[0]: li.split()[1:] for li in ok.stdout.splitlines()[2:5]}
    assert rows["r1"] == ["-", "cut", "cut"] and rows["r2"] == ["cut", "-", "0%"]
    assert "0.0% dropped (4/4 received over the linked pairs)" in ok.stdout
    # The medium links r2 and r3, but r3's interface goes down behind netlab's back.
    assert netlab("exec", name, "r3", "--", "ip", "link", "set", "eth0", "down").returncode == 0
    bad = netlab("pingall", name, "--count", "1")
    assert bad.returncode == 1
    assert "FAIL r2 -> r3: linked by the medium, no reply" in bad.stdout


FAILING = """
@pytest.mark.fleet(n=2)
def test_that_fails(fleet):
    fleet.stop("r1")
    assert False, "on purpose"
"""


def test_a_failed_test_keeps_its_daemon_logs_where_the_report_says(tmp_path: Path) -> None:
    (tmp_path / "conftest.py").write_text('pytest_plugins = ["tests.support.fleets"]\n')
    (tmp_path / "test_fails.py").write_text("import pytest\n" + textwrap.dedent(FAILING))
    kept = tmp_path / "kept"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "SDFR_KEEP_LOGS": str(kept)}
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "test_fails.py"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert run.returncode == 1, run.stdout + run.stderr
    said = [li for li in run.stdout.splitlines() if "daemon logs kept in" in li]
    assert len(said) == 1, run.stdout
    folder = Path(said[0].split("daemon logs kept in ")[1].split(" (")[0])
    assert folder.is_relative_to(kept) and "test_that_fails" in str(folder)
    for robot in ("r1", "r2"):  # the log netlab's header starts, with the daemon's lines
        log = (folder / robot / "sdfrd.log").read_text()
        assert log.startswith("--- netlab: ") and log.count("\n") > 1, log
    assert not list(folder.glob("*/state/api.sock"))  # sockets are not copied
