"""Reading /proc: one parser of /proc/PID/stat for the daemon, netlab, the benches and tests;
and the one prctl that ties a child's life to its parent's."""

from __future__ import annotations

import signal
from collections.abc import Mapping
from pathlib import Path

PROC = Path("/proc")
#: The name sdfrd's supervisor gives each layer it forks, in `ps -o comm` and /proc/PID/comm
#: (at most 15 bytes): how a layer is told apart from its supervisor, whose command line it
#: shares.
LAYER_COMM = {"api": "sdfrd-api", "discovery": "sdfrd-discovery"}

_PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """prctl(PR_SET_PDEATHSIG, SIGKILL): this process ends when its parent does (in a forked
    child: sdfrd's layers, a bench node's daemons).  ctypes is imported here, on first use: a
    caller that forks imports it before, so that its children share it."""
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)


def stat_fields(pid: int, proc: Path = PROC) -> list[str] | None:
    """The fields of /proc/PID/stat from the state on (field 3: state, 4: parent pid, ...);
    None when the process is gone. The command name before them may hold anything, spaces
    and parentheses included: the fields start after its last ')'."""
    try:
        text = (proc / str(pid) / "stat").read_text()
    except (OSError, ValueError):
        return None
    _, paren, rest = text.rpartition(")")
    return rest.split() if paren else None


def running(pid: int, proc: Path = PROC) -> bool:
    """True while `pid` exists and is not a zombie."""
    fields = stat_fields(pid, proc)
    return fields is not None and bool(fields) and fields[0] != "Z"


def thread_running(pid: int, tid: int, proc: Path = PROC) -> bool:
    """True while thread `tid` of process `pid` exists and is not a zombie."""
    return running(tid, proc / str(pid) / "task")


def start_time(pid: int, proc: Path = PROC) -> int | None:
    """When `pid` started, in clock ticks since boot (stat field 22): tells a process from a
    later one that reuses its pid."""
    fields = stat_fields(pid, proc)
    return int(fields[19]) if fields is not None and len(fields) > 19 else None


def parent_map(proc: Path = PROC) -> dict[int, list[int]]:
    """parent pid -> its children's pids, for every process now."""
    out: dict[int, list[int]] = {}
    for entry in proc.iterdir():
        if not entry.name.isdigit():
            continue
        fields = stat_fields(int(entry.name), proc)
        if fields is None or len(fields) < 2 or not fields[1].isdigit():
            continue
        out.setdefault(int(fields[1]), []).append(int(entry.name))
    return out


def tree(pid: int, kids: Mapping[int, list[int]]) -> list[int]:
    """`pid` and all its descendants (from a `parent_map()`), sorted."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo.extend(kids.get(p, ()))
    return sorted(out)
