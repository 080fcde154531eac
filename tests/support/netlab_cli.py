"""The `netlab` command as the namespace tier's tests run it: in a child Python, no stdin."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator

from netlab import manifest
from tests.support.fleets import unique_lab_name


def netlab(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "netlab.cli", *args],
        capture_output=True, text=True, timeout=timeout, stdin=subprocess.DEVNULL,
    )  # fmt: skip


def cli_lab() -> Iterator[str]:
    """A fixture's body: a unique lab name, the lab taken down (folder and all) after the test,
    which fails if its manifest is left."""
    lab = unique_lab_name()
    yield lab
    netlab("down", lab, "--cleanup")
    assert manifest.load(lab) is None
