"""Every benchmark's --help prints its usage and runs nothing (a help string with a bare "%"
made side_by_side's --help a traceback; bench.events ignored --help and ran)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[3] / "bench"
MAINS = sorted(p.stem for p in BENCH.glob("*.py") if 'if __name__ == "__main__"' in p.read_text())


def test_the_benchmarks_are_found() -> None:
    assert {"side_by_side", "events", "paper", "scale"} <= set(MAINS)


@pytest.mark.parametrize("module", MAINS)
def test_a_benchmark_s_help_is_its_usage(module: str) -> None:
    done = subprocess.run(
        [sys.executable, "-m", f"bench.{module}", "--help"],
        cwd=BENCH.parent,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage:"), done.stdout[:300]
