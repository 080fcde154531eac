"""A 200 that confirms a registration is on disk, as a 201 is: a power cut right after it
keeps what it said (needs root: an ext4 image on a loop device)."""

from __future__ import annotations

import contextlib
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from sdfr.client import Client
from sdfr.store import Store
from tests.support.api import ApiLayer

pytestmark = pytest.mark.root


def run(*argv: str) -> str:
    done = subprocess.run(argv, capture_output=True, text=True, timeout=60)
    if done.returncode != 0:
        raise AssertionError(f"{' '.join(argv)}: {done.stderr.strip()}")
    return done.stdout.strip()


@contextlib.contextmanager
def on_image(image: Path, at: Path) -> Iterator[Path]:
    """`image` on a loop device, mounted at `at`; both undone after."""
    device = run("losetup", "-f", "--show", str(image))
    try:
        at.mkdir(parents=True, exist_ok=True)
        run("mount", device, str(at))
        try:
            yield at
        finally:
            subprocess.run(["umount", "-l", str(at)], capture_output=True, timeout=60)
    finally:
        subprocess.run(["losetup", "-d", device], capture_output=True, timeout=60)


def test_a_publish_confirmed_by_a_200_survives_a_power_cut(tmp_path: Path) -> None:
    """A program publishes with a 60 s lease, then publishes again (a retry, or a new ttl):
    200, lease 600 s. The image is copied right after that 200, as the disk holds it (a
    power cut); mounted again, the copy holds the 600 s lease."""
    image, copy = tmp_path / "disk.img", tmp_path / "after-power-cut.img"
    run("truncate", "-s", "64M", str(image))
    run("mkfs.ext4", "-q", "-F", str(image))
    with on_image(image, tmp_path / "disk") as disk:
        (disk / "state").mkdir()
        api = ApiLayer(disk / "state")
        api.start()
        try:
            with Client(api.api) as c:
                c.publish("lidar", "sensor.lidar", service_id="lidar-1", ttl=60)
                again = c.publish_service("lidar", "sensor.lidar", service_id="lidar-1", ttl=600)
                assert again["ttl"] == 600.0
                shutil.copyfile(image, copy)  # the power cut, right after the 200
        finally:
            api.kill()
    with on_image(copy, tmp_path / "rebooted") as disk:
        store = Store(disk / "state")
        try:
            lease = store.lease("lidar-1")
        finally:
            store.close()
    assert lease is not None and lease.ttl == 600.0, lease
