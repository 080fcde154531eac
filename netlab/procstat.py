"""CPU time and memory of process trees, read from /proc (Linux).

A robot's sdfrd is a supervisor with two children (the API and discovery layers); what the
daemon costs is the sum over that tree.  `Usage.read(pids)` takes one reading; the CPU share
over a window is the difference of two readings divided by the wall time between them.

PSS (proportional set size, from ``smaps_rollup``) shares the pages several processes map
(the Python interpreter, shared libraries) among them, so PSS summed over 50 daemons is the
memory they really take; RSS counts shared pages once per process.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sdfr import procfs

__all__ = ["Usage", "children", "tree", "window"]

_TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
_PAGE_KB = (os.sysconf("SC_PAGE_SIZE") // 1024) if hasattr(os, "sysconf") else 4


def children(proc: Path = Path("/proc")) -> dict[int, list[int]]:
    """parent pid -> its children's pids, for every process now."""
    return procfs.parent_map(proc)


tree = procfs.tree


def _kb(path: Path, key: str) -> int:
    try:
        for line in path.read_text().splitlines():
            if line.startswith(key):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return 0


@dataclass(frozen=True)
class Usage:
    """One reading of a process tree: CPU seconds used so far, memory now (KiB)."""

    time: float
    cpu_s: float
    rss_kb: int
    pss_kb: int
    processes: int

    @classmethod
    def read(cls, pids: Iterable[int], proc: Path = Path("/proc")) -> Usage:
        cpu = 0.0
        rss = pss = n = 0
        for pid in pids:
            fields = procfs.stat_fields(pid, proc)
            if fields is None or len(fields) < 22:
                continue  # gone since it was listed
            # utime and stime are fields 14 and 15 of stat (1-based), 12 and 13 here.
            cpu += (int(fields[11]) + int(fields[12])) / _TICK
            rss += int(fields[21]) * _PAGE_KB
            pss += _kb(proc / str(pid) / "smaps_rollup", "Pss:")
            n += 1
        return cls(time.monotonic(), cpu, rss, pss, n)


def window(start: Usage, end: Usage) -> dict[str, Any]:
    """What a tree used between two readings: CPU as % of one core, memory at the end (MiB)."""
    wall = end.time - start.time
    cpu = 100.0 * (end.cpu_s - start.cpu_s) / wall if wall > 0 else 0.0
    return {
        "cpu_percent": round(max(0.0, cpu), 2),
        "cpu_s": round(max(0.0, end.cpu_s - start.cpu_s), 3),
        "wall_s": round(wall, 3),
        "rss_mib": round(end.rss_kb / 1024, 1),
        "pss_mib": round(end.pss_kb / 1024, 1),
        "processes": end.processes,
    }
