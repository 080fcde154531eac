"""The shipped systemd unit under a real systemd: PID 1 of a container booted from this
machine's own file system (systemd-nspawn --volatile=yes; this machine's PID 1 is not
systemd). sdfrd becomes active only once it says READY=1, with its STATUS= line and the
StateDirectory made; a SIGSTOPped supervisor misses the watchdog and systemd restarts it."""

from __future__ import annotations

import contextlib
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from sdfr.cli import example_text

pytestmark = pytest.mark.root

REPO = Path(__file__).resolve().parents[2]
# What the probe unit does inside the container, writing what it saw to /out.
PROBE = """[Unit]
Description=probe sdfrd under a real systemd
Wants=sdfrd.service
After=sdfrd.service

[Service]
Type=oneshot
ExecStart=/bin/sh -c '\\
  systemctl show sdfrd -p ActiveState -p StatusText -p Type -p WatchdogUSec > /out/ready.txt; \\
  {sdfr} health > /out/health.txt 2>&1; \\
  stat -c %%a /var/lib/sdfr > /out/statedir.txt; \\
  kill -STOP $(systemctl show -p MainPID --value sdfrd); \\
  sleep 12; \\
  systemctl show sdfrd -p ActiveState -p NRestarts > /out/after.txt; \\
  journalctl -u sdfrd --no-pager > /out/journal.txt; \\
  systemctl poweroff'
"""


def test_the_unit_under_systemd(tmp_path: Path) -> None:
    nspawn = shutil.which("systemd-nspawn")
    if nspawn is None:
        pytest.fail("systemd-nspawn is missing: `make test` installs systemd-container")
    venv_bin = Path(sys.executable).parent
    units, out, etc = tmp_path / "units", tmp_path / "out", tmp_path / "etc"
    for d in (units, out, etc, units / "sdfrd.service.d"):
        d.mkdir()
    unit = example_text("sdfrd.service").replace("/usr/local/bin/sdfrd", str(venv_bin / "sdfrd"))
    (units / "sdfrd.service").write_text(unit)
    # The test's only changes to the unit: a short watchdog, /root visible (this test's
    # interpreter may live there, as pyenv's does), and /tmp shared when the checkout or
    # its interpreter lives there (a CI clone may): PrivateTmp would hide sdfrd itself.
    under_tmp = any(
        p.is_relative_to("/tmp") for p in (REPO, venv_bin.resolve(), Path(sys.executable).resolve())
    )
    (units / "sdfrd.service.d" / "test.conf").write_text(
        "[Service]\nWatchdogSec=4\nProtectHome=no\n" + ("PrivateTmp=no\n" if under_tmp else "")
    )
    (units / "sdfr-probe.service").write_text(PROBE.format(sdfr=venv_bin / "sdfr"))
    (etc / "robot.toml").write_text(
        '[sdfrd]\niface = "lo"\nrobot_id = "c1"\napi = "127.0.0.1:8700"\n'
        'describe = "127.0.0.1:8701"\nbeacon_interval = 1.0\n'
    )
    interpreter = Path(sys.executable).resolve().parents[1]
    argv = [
        nspawn, "-D", "/", "--volatile=yes", "--register=no", "--keep-unit",
        "--private-network", "--console=pipe", "--machine", f"sdfrt{tmp_path.name[-6:]}",
        f"--bind-ro={REPO}", f"--bind-ro={interpreter}", f"--bind-ro={venv_bin.parent}",
        f"--bind={out}:/out", f"--bind-ro={etc}:/etc/sdfr",
        *(f"--bind-ro={units / n}:/etc/systemd/system/{n}"
          for n in ("sdfrd.service", "sdfrd.service.d", "sdfr-probe.service")),
        # The container has only lo: waiting for network-online would take networkd's 2 min.
        "--bind-ro=/dev/null:/etc/systemd/system/systemd-networkd-wait-online.service",
        "-b", "--", "--unit=sdfr-probe.service",
    ]  # fmt: skip
    proc = subprocess.Popen(
        argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, stdin=subprocess.DEVNULL
    )
    try:
        _, err = proc.communicate(timeout=300)
    finally:
        # nspawn halts its container on SIGTERM (SIGKILL would leave the container's
        # systemd running, re-parented to our PID 1); a second SIGTERM ends it at once.
        for _ in range(2):
            if proc.poll() is None:
                proc.terminate()
                with contextlib.suppress(subprocess.TimeoutExpired):
                    proc.wait(15)
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    seen = {p.name: p.read_text() for p in out.iterdir()}
    assert "after.txt" in seen, f"the container did not finish: {err[-2000:]} {seen}"
    ready = seen["ready.txt"]
    assert "ActiveState=active" in ready and "Type=notify" in ready, ready
    assert "StatusText=serving the API on 127.0.0.1:8700" in ready, ready
    assert "WatchdogUSec=4s" in ready
    assert "api up, discovery up" in seen["health.txt"], seen["health.txt"]
    assert seen["statedir.txt"].strip() == "750"
    after = seen["after.txt"]
    assert "NRestarts=1" in after and "ActiveState=active" in after, after
    assert "Watchdog timeout" in seen["journal.txt"], seen["journal.txt"][-3000:]
