"""Benchmarks: `make bench` runs them and writes JSON."""

from __future__ import annotations

import compileall
import sys
from pathlib import Path

import sdfr


def err(text: str) -> None:
    """A line on stderr at once: the benches' progress and tables."""
    print(text, file=sys.stderr, flush=True)


def compile_sdfr() -> dict[str, object]:
    """Write the bytecode of sdfr's modules (`__pycache__`) before a bench starts daemons, as
    `pip install` does: a daemon that finds none (a checkout run with PYTHONDONTWRITEBYTECODE
    set, as on this machine) compiles every module in memory at each start, and the compiler's
    scratch stays in its heap: about 2 MiB more per daemon than an installed sdfrd takes.
    What it did goes in the bench's JSON ("bytecode")."""
    package = Path(sdfr.__file__).parent
    ok = compileall.compile_dir(str(package), quiet=1)
    if not ok:
        raise SystemExit(f"bench: cannot write the bytecode of {package} (see above)")
    return {
        "package": str(package),
        "compiled": True,
        "dont_write_bytecode": sys.dont_write_bytecode,
    }
