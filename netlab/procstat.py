"""CPU time and memory of process trees, read from /proc (Linux).

A robot's sdfrd is a supervisor with two children (the API and discovery layers); what the
daemon costs is the sum over that tree.  `Usage.read(pids)` takes one reading; the CPU share
over a window is the difference of two readings divided by the wall time between them.

PSS (proportional set size, from ``smaps_rollup``) shares the pages several processes map
(the Python interpreter, shared libraries) among them, so PSS summed over 50 daemons is the
memory they really take; RSS counts shared pages once per process.
"""

from __future__ import annotations

import contextlib
import os
import struct
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sdfr.host import procfs

#: A forked layer's /proc/PID/comm -> its name.
LAYER_COMMS = {comm: layer for layer, comm in procfs.LAYER_COMM.items()}

__all__ = ["Memory", "Usage", "children", "frames", "memory", "rollup", "tree", "window"]

_TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
_PAGE_KB = (os.sysconf("SC_PAGE_SIZE") // 1024) if hasattr(os, "sysconf") else 4


def layer_of(pid: int, proc: Path = Path("/proc")) -> str:
    """Which part of a sdfrd tree a process is: "api" or "discovery" (the names the supervisor
    gives its forked layers in /proc/PID/comm), "supervisor" (sdfrd itself), "other" (not
    sdfrd's: a tree may hold a program the daemon started) or "gone"."""
    try:
        comm = (proc / str(pid) / "comm").read_text().strip()
        cmd = (proc / str(pid) / "cmdline").read_bytes()
    except OSError:
        return "gone"
    if comm in LAYER_COMMS:
        return LAYER_COMMS[comm]
    return "supervisor" if b"sdfrd" in cmd or b"sdfr.daemon" in cmd else "other"


def threads(pid: int, proc: Path = Path("/proc")) -> dict[int, str]:
    """The threads of `pid` alive now: thread id -> name (comm); none if it is gone."""
    out = {}
    try:
        for task in (proc / str(pid) / "task").iterdir():
            with contextlib.suppress(OSError):  # (a thread that just ended)
                out[int(task.name)] = (task / "comm").read_text().strip()
    except (OSError, ValueError):
        pass
    return out


def layer_threads(pid: int, proc: Path = Path("/proc")) -> dict[str, int]:
    """The layers that run as threads of `pid` (sdfrd --layers threads): layer -> thread id."""
    return {
        LAYER_COMMS[comm]: tid
        for tid, comm in threads(pid, proc).items()
        if tid != pid and comm in LAYER_COMMS
    }


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

    @classmethod
    def read_thread(cls, pid: int, tid: int, proc: Path = Path("/proc")) -> Usage:
        """One thread of `pid`: its CPU seconds (its memory is its process's: 0 here)."""
        one = cls.read([tid], proc / str(pid) / "task")
        return cls(one.time, one.cpu_s, 0, 0, one.processes)


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


@dataclass(frozen=True)
class Memory:
    """One process's memory now (KiB): RSS, PSS and USS (its private pages) from the kernel,
    and `alone`, its share of the pages when only the processes it was measured with (its
    daemon's tree) count (see `memory`)."""

    pid: int
    rss_kb: int
    pss_kb: int
    uss_kb: int
    alone_kb: int

    def to_json(self) -> dict[str, Any]:
        return {
            "pid": self.pid,
            "rss_mib": round(self.rss_kb / 1024, 2),
            "pss_mib": round(self.pss_kb / 1024, 2),
            "uss_mib": round(self.uss_kb / 1024, 2),
            "alone_mib": round(self.alone_kb / 1024, 2),
        }


def rollup(pid: int, proc: Path = Path("/proc")) -> dict[str, int]:
    """/proc/PID/smaps_rollup as {field: KiB} ({} when the process is gone)."""
    out: dict[str, int] = {}
    try:
        text = (proc / str(pid) / "smaps_rollup").read_text()
    except OSError:
        return out
    for line in text.splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[2] == "kB":
            out[parts[0].rstrip(":")] = int(parts[1])
    return out


_PRESENT = 1 << 63
_PFN_MASK = (1 << 55) - 1


def frames(pid: int, proc: Path = Path("/proc")) -> set[int] | None:
    """The physical page frames `pid` maps now (None: unreadable, e.g. not root).

    /proc/PID/pagemap gives each virtual page's frame number to root only (zeros otherwise).
    """
    base = proc / str(pid)
    found: set[int] = set()
    try:
        maps = (base / "maps").read_text().splitlines()
        with (base / "pagemap").open("rb", buffering=0) as pagemap:
            for line in maps:
                span, _, rest = line.partition(" ")
                if rest.rstrip().endswith("[vsyscall]"):
                    continue
                lo, _, hi = span.partition("-")
                start, end = int(lo, 16) // 4096, int(hi, 16) // 4096
                pagemap.seek(start * 8)
                data = pagemap.read((end - start) * 8)
                for (entry,) in struct.iter_unpack("<Q", data):
                    if entry & _PRESENT:
                        found.add(entry & _PFN_MASK)
    except OSError:
        return None
    if found == {0}:
        return None  # frame numbers hidden: not root
    return found


def memory(pids: Iterable[int], proc: Path = Path("/proc")) -> list[Memory]:
    """RSS, PSS, USS of each process, and its PSS as if only `pids` ran on the machine.

    The kernel's PSS divides a page shared by k processes by k, whatever they are: the
    same daemon's PSS falls when other Python programs run beside it (they share the
    interpreter's pages). `alone` divides only among `pids` (a daemon's tree): the memory
    the daemon takes on a machine where nothing else maps those pages; the sum over a tree
    is the number of distinct pages it maps. It is 0 when frames cannot be read (not root).
    """
    pids = list(pids)
    sets = {pid: frames(pid, proc) for pid in pids}
    count: dict[int, int] = {}
    for found in sets.values():
        for frame in found or ():
            count[frame] = count.get(frame, 0) + 1
    page_kb = _PAGE_KB
    out = []
    for pid in pids:
        r = rollup(pid, proc)
        if not r:
            continue
        found = sets[pid]
        alone = 0.0 if found is None else sum(1.0 / count[f] for f in found) * page_kb
        uss = r.get("Private_Clean", 0) + r.get("Private_Dirty", 0)
        out.append(Memory(pid, r.get("Rss", 0), r.get("Pss", 0), uss, round(alone)))
    return out
