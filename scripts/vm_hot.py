"""The files a VM tier's Python processes read at start, for scripts/vm.sh to copy into the
guest's memory before the tests run.

The guest reads the host's filesystem over 9p without a page cache (virtme-ng's root), under
software emulation: every interpreter start reads libpython again, and every import its
module and bytecode files, through the emulated virtio device.  Measured in the netem VM
(2026-11-28): `python -c pass` 2.3 s, importing sdfrd's layers 11.7 s, netlab's scenario
engine 32 s; with these files in a tmpfs laid over their folders, 1.4 s, 6.6 s and 15 s.

Usage: python scripts/vm_hot.py TESTDIR...  prints one absolute path per line: the files of
every module that importing the tier's test modules, pytest and the daemon's and netlab's
run-time modules loads (source, bytecode, extension), the interpreter and the shared
libraries it links.  Bytecode missing here (PYTHONDONTWRITEBYTECODE=1, or a fresh checkout)
is compiled first: the guest cannot write it, and would compile every module in every
process.  Run it with the interpreter the VM runs (.venv/bin/python), from the repository's
root.  A module that cannot be imported here is left out (it is then read over
9p, as before): the list only makes the guest faster, never different.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import py_compile
import subprocess
import sys
from pathlib import Path

#: Imported by the processes the tiers start (sdfrd's layers, netlab's helpers), not by the
#: test modules themselves.
RUNTIME = (
    "pytest",
    "_pytest.junitxml",
    "sdfr.daemon.supervisor",
    "sdfr.daemon.discovery",
    "sdfr.daemon.apiserver",
    "sdfr.api.app",
    "sdfr.host.wifi",
    "sdfr.cli",
    "netlab.scenario",
    "netlab.lab",
    "netlab.airmedium",
    "netlab.pcap",
    "netlab.report",
)


def test_modules(folders: list[str]) -> list[str]:
    out = []
    for folder in folders:
        for path in sorted(Path(folder).rglob("*.py")):
            out.append(".".join(path.with_suffix("").parts))
    return out


def main(folders: list[str]) -> int:
    sys.path.insert(0, os.getcwd())
    for name in [*RUNTIME, *test_modules(folders)]:
        try:
            importlib.import_module(name)
        except KeyboardInterrupt:
            raise
        except BaseException as exc:  # pytest's skip is one: left to 9p, and said
            print(f"vm_hot: {name} not listed: {exc!r}", file=sys.stderr)
    paths: set[str] = set()
    for module in list(sys.modules.values()):
        file = getattr(module, "__file__", None)
        if not file or not os.path.isfile(file):
            continue
        paths.add(os.path.realpath(file))
        if file.endswith(".py"):
            cached = importlib.util.cache_from_source(file)
            if not os.path.isfile(cached):  # e.g. PYTHONDONTWRITEBYTECODE=1 here
                py_compile.compile(file, cfile=cached, doraise=False, quiet=2)
            if os.path.isfile(cached):
                paths.add(os.path.realpath(cached))
    exe = os.path.realpath(sys.executable)
    paths.add(exe)
    linked = subprocess.run(["ldd", exe], capture_output=True, text=True, check=False).stdout
    for word in linked.split():
        if word.startswith("/") and os.path.isfile(word):
            paths.add(os.path.realpath(word))
    for path in sorted(paths):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
