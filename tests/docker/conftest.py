"""The docker tier: Docker's engine (installed and started when missing, and stopped again
if this session started it) and the robot image, built once per session.

It needs root.  When Docker cannot run, its tests fail saying why; SDFR_SKIP_DOCKER=1 skips
them and says so.
"""

from __future__ import annotations

import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from sdfr import __version__

REPO = Path(__file__).resolve().parents[2]
SKIP = os.environ.get("SDFR_SKIP_DOCKER") == "1"


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if not SKIP:
        return
    mark = pytest.mark.skip(reason="SDFR_SKIP_DOCKER=1: the docker tier is skipped")
    for item in items:
        if Path(str(item.fspath)).is_relative_to(Path(__file__).parent):
            item.add_marker(mark)


def run(*argv: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        list(argv), cwd=REPO, capture_output=True, text=True, timeout=timeout,
        stdin=subprocess.DEVNULL,
    )  # fmt: skip


IMAGE = "sdfr-robot"
TAGS = (f"{IMAGE}:{__version__}", f"{IMAGE}:latest")


def _present(tag: str) -> bool:
    return run("docker", "image", "inspect", tag).returncode == 0


@pytest.fixture(scope="session")
def image() -> Iterator[str]:
    """The robot image, built from this checkout (Docker started first when needed).  Tags
    the session made are removed after it, with the layers they leave dangling; the Debian
    base (sdfr-base:local) is kept, for the next build on this machine."""
    if os.geteuid() != 0:
        pytest.fail("the docker tier needs root (set SDFR_SKIP_DOCKER=1 to skip it)")
    # A dockerd that answers already is someone else's (another session, the user's): it
    # stays.  One this session starts is stopped after it.
    ours = run("docker", "info").returncode != 0
    up = run("bash", "scripts/docker-up.sh", timeout=900)
    if up.returncode != 0:
        pytest.fail(f"Docker cannot run here:\n{up.stdout}{up.stderr}")
    had = {tag for tag in TAGS if _present(tag)}
    try:
        res = run("bash", "scripts/image.sh", timeout=1800)
        if res.returncode != 0:
            pytest.fail(f"cannot build the robot image:\n{res.stdout}{res.stderr}")
        yield TAGS[-1]
    finally:
        made = [tag for tag in TAGS if tag not in had and _present(tag)]
        if made:
            run("docker", "image", "rm", *made)
        run(
            "docker",
            "image",
            "prune",
            "-f",
            "--filter",
            f"label=org.opencontainers.image.title={IMAGE}",
        )
        if ours:
            run("bash", "scripts/docker-down.sh")
