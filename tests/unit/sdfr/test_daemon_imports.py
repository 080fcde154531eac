"""What a running daemon carries: nothing imported that the default daemon does not use, and
glibc malloc's thresholds pinned. Each costs memory that the footprint bench counts."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from sdfr.daemon import MALLOC_TUNABLES

# A daemon as a service manager starts it: plain flags, both layers imported (preload).
DAEMON = """
import sys
from sdfr.daemon import NOT_LOADED
for name in NOT_LOADED:
    sys.modules.setdefault(name, None)
from sdfr.daemon import supervisor
from sdfr.config.load import from_args
from_args(["--iface", "eth0", "--fleet=2", "--state-dir", "/x", "--layers", "threads"])
supervisor.preload()
print(" ".join(sorted(m for m, v in sys.modules.items() if v is not None)))
"""

NOT_IMPORTED = {
    "argparse": "flags are read without it when plain (sdfr.config.load._plain_flags)",
    "shutil": "argparse's help formatter imports it",
    "ctypes": "only --layers processes uses it",
    "sdfr.protocol.addressing": "only --addressing auto",
    "sdfr.daemon.arp": "only --addressing auto",
    "difflib": "only a mistake's hint",
    "tomllib": "only --config",
}


def test_the_daemon_imports_nothing_it_does_not_use() -> None:
    out = subprocess.run(
        [sys.executable, "-c", DAEMON], capture_output=True, text=True, check=True
    ).stdout.split()
    assert "sdfr.daemon.discovery" in out and "sdfr.daemon.apiserver" in out
    loaded = {name: why for name, why in NOT_IMPORTED.items() if name in out}
    assert not loaded, f"the daemon imports {loaded}"


# Runs pin_malloc as sdfrd's main does, then says what its process got: the exec'd
# process runs this same code again and prints; the first never gets to print.
PIN = """
import os, sys
from sdfr.daemon import pin_malloc
pin_malloc()
print(os.environ.get("GLIBC_TUNABLES"), os.environ.get("MALLOC_ARENA_MAX"))
"""


def _pinned(env: dict[str, str]) -> str:
    clean = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
    clean = {k: v for k, v in clean.items() if not k.startswith("MALLOC_")}
    return subprocess.run(
        [sys.executable, "-c", PIN], env=clean | env, capture_output=True, text=True, check=True
    ).stdout.strip()


def _glibc() -> bool:
    try:
        return bool(os.confstr("CS_GNU_LIBC_VERSION"))
    except (ValueError, OSError):
        return False


@pytest.mark.skipif(not _glibc(), reason="glibc only")
def test_sdfrd_runs_with_glibc_malloc_thresholds_pinned() -> None:
    assert _pinned({}) == f"{MALLOC_TUNABLES} None"


def test_a_users_own_malloc_settings_are_left_alone() -> None:
    assert _pinned({"GLIBC_TUNABLES": "glibc.malloc.arena_max=2"}) == (
        "glibc.malloc.arena_max=2 None"
    )
    assert _pinned({"MALLOC_ARENA_MAX": "1"}) == "None 1"
