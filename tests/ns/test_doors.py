"""The robot's own doors under abuse, with real daemons (needs root): a flood of connections
to the description server, a full state directory, and a power cut."""

from __future__ import annotations

import contextlib
import errno
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from netlab import procstat
from netlab.lab import Lab
from sdfr.client import Client
from sdfr.errors import ApiError
from sdfr.store import Store
from tests.support.api import ApiLayer
from tests.support.waiting import poll

pytestmark = pytest.mark.root

ROOT = Path(__file__).resolve().parents[2]
BEACON = 1.0


def run(*argv: str) -> str:
    done = subprocess.run(argv, capture_output=True, text=True, timeout=60)
    if done.returncode != 0:
        raise AssertionError(f"{' '.join(argv)}: {done.stderr.strip()}")
    return done.stdout.strip()


@contextlib.contextmanager
def mounted(*argv: str, at: Path) -> Iterator[Path]:
    at.mkdir(parents=True, exist_ok=True)
    run("mount", *argv, str(at))
    try:
        yield at
    finally:
        subprocess.run(["umount", "-l", str(at)], capture_output=True, timeout=60)


def fill(path: Path) -> None:
    """Write to `path` until its filesystem is full."""
    with path.open("wb") as f:
        chunk = b"\0" * 65536
        try:
            while True:
                f.write(chunk)
                f.flush()
        except OSError as exc:
            assert exc.errno == errno.ENOSPC, exc


# -- the description server cannot starve the local API ------------------------------------------


HOLD = """
import socket, sys, time
socks, refused = [], 0
for _ in range(int(sys.argv[2])):
    s = socket.socket()
    s.setblocking(False)
    try:
        s.connect((sys.argv[1], 8701))
    except BlockingIOError:
        pass
    except OSError:
        refused += 1
        continue
    socks.append(s)
print(len(socks), refused, flush=True)
time.sleep(float(sys.argv[3]))
"""


def test_a_thousand_idle_connections_to_the_description_leave_the_api_answering(
    fleet_factory: Callable[..., Lab],
) -> None:
    lab = fleet_factory(2, beacon=BEACON, start=False)
    lab.add_robot("x9")
    lab.start_all(["r1", "r2"], beacon_interval=BEACON)
    pid = lab.daemon_pid("r1")
    assert pid is not None
    for p in procstat.tree(pid, procstat.children()):  # `ulimit -n 1024`, the common default
        run("prlimit", f"--pid={p}", "--nofile=1024:1024")
    log_before = lab.robot("r1").log.stat().st_size
    holder = lab.popen(
        "x9",
        [sys.executable, "-c", HOLD, lab.robot("r1").ip, "1100", "8"],
        stdout=subprocess.PIPE,
        text=True,
    )
    worst = 0.0
    try:
        time.sleep(2.0)  # the connections are open (or tried) by now
        with Client(unix_socket=lab.robot("r1").api_socket, timeout=5) as c:
            end = time.monotonic() + 4.0
            while time.monotonic() < end:
                t0 = time.perf_counter()
                c.neighbors()
                c.publish("probe", "t", service_id="probe")  # a write works as well
                worst = max(worst, time.perf_counter() - t0)
                time.sleep(0.05)
        # Inside the robot, over TCP, as a program would.
        done = lab.exec("r1", [sys.executable, "-m", "sdfr.cli", "neighbors", "--json"])
        assert done.returncode == 0, done.stderr
    finally:
        out, _ = holder.communicate(timeout=30)
    assert worst < 0.1, f"the local API took {worst * 1000:.0f} ms"
    status = lab.client("r1").self_info()
    assert status["discovery"]["up"]
    grown = lab.robot("r1").log.stat().st_size - log_before
    assert grown < 100_000, f"the log grew {grown} bytes"
    print(f"\n  outsider opened/refused {out.strip()}; local API worst {worst * 1000:.1f} ms")


# -- a full state directory ---------------------------------------------------------------------


def test_a_full_state_dir_is_named_and_outlived(
    fleet_factory: Callable[..., Lab],
) -> None:
    lab = fleet_factory(2, beacon=BEACON, start=False)
    state = lab.robot("r1").state_dir
    with mounted("-t", "tmpfs", "-o", "size=16m", "tmpfs", at=state):
        try:
            lab.start_all(beacon_interval=BEACON)
            c = lab.client("r1")
            c.publish("before", "t")
            filler = state / "filler"
            fill(filler)
            with pytest.raises(ApiError) as err:
                c.publish("during", "t")
            assert err.value.status == 507 and "full" in str(err.value), err.value
            health = c.health()
            assert (health["status"], health["discovery"], health["state"]) == (
                "degraded",
                "up",
                "full",
            )
            # Longer than a heartbeat may be stale: the discovery layer, which cannot write
            # its status file any more, is still known to be up, and says the disk is full.
            time.sleep(4.0)
            health = c.health()
            assert (health["discovery"], health["state"]) == ("up", "full"), health
            filler.unlink()
            c.publish("after", "t")
            poll("healthy again", lambda: c.health()["status"] == "ok", 5.0)

            names = {s["name"] for s in c.services()}
            assert names == {"before", "after"}
            poll("r2 lists what r1 published",
                 lambda: {s["name"] for n in lab.client("r2").neighbors() for s in n["services"]}
                 == names, 5.0)  # fmt: skip
        finally:
            for robot in ("r1", "r2"):
                if lab.alive(robot):
                    lab.stop(robot)


# -- a power cut -----------------------------------------------------------------------------------


def test_no_acknowledged_publish_is_lost_in_a_power_cut(tmp_path: Path) -> None:
    """The state on an ext4 image; right after 20 acknowledged publishes the image is copied
    as the disk holds it (what the kernel has not written to the device is not in the copy:
    a power cut); the copy, mounted again (journal replayed), holds all 20."""
    image, copy = tmp_path / "disk.img", tmp_path / "after-power-cut.img"
    run("truncate", "-s", "64M", str(image))
    run("mkfs.ext4", "-q", "-F", str(image))
    device = run("losetup", "-f", "--show", str(image))
    try:
        with mounted(device, at=tmp_path / "disk") as disk:
            api = ApiLayer(disk / "state")
            (disk / "state").mkdir()
            api.start()
            try:
                with Client(api.api) as c:
                    ids = [c.publish(f"service {i}", "sensor.kind") for i in range(20)]
                shutil.copyfile(image, copy)  # the power cut, right after the last 201
            finally:
                api.kill()
    finally:
        subprocess.run(["losetup", "-d", device], capture_output=True, timeout=60)
    device = run("losetup", "-f", "--show", str(copy))
    try:
        with mounted(device, at=tmp_path / "rebooted") as disk:
            store = Store(disk / "state")
            try:
                version, services = store.local_state()
            finally:
                store.close()
    finally:
        subprocess.run(["losetup", "-d", device], capture_output=True, timeout=60)
    assert sorted(s.id for s in services) == sorted(ids) and version == 20
