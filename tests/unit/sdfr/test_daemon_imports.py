"""What a running daemon does not import: each of these costs memory that the footprint
bench counts (issue 16), for a feature the default daemon does not use."""

from __future__ import annotations

import subprocess
import sys

# A daemon as a service manager starts it: plain flags, both layers imported (preload).
DAEMON = """
import sys
from sdfr.daemon import NOT_LOADED
for name in NOT_LOADED:
    sys.modules.setdefault(name, None)
from sdfr.daemon import supervisor
from sdfr.config import from_args
from_args(["--iface", "eth0", "--fleet=2", "--state-dir", "/x", "--layers", "threads"])
supervisor.preload()
print(" ".join(sorted(m for m, v in sys.modules.items() if v is not None)))
"""

NOT_IMPORTED = {
    "argparse": "flags are read without it when plain (sdfr.config._plain_flags)",
    "shutil": "argparse's help formatter imports it",
    "ssl": "nothing the daemon serves is TLS",
    "ctypes": "only --layers processes uses it",
    "sdfr.addressing": "only --addressing auto",
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
