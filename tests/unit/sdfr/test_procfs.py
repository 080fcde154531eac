"""The one /proc/PID/stat parser."""

from __future__ import annotations

import os
from pathlib import Path

from sdfr.host import procfs


def fake_proc(tmp_path: Path, procs: dict[int, tuple[str, str, int]]) -> Path:
    """pid -> (command name, state, parent pid) as /proc shows them."""
    for pid, (comm, state, ppid) in procs.items():
        (tmp_path / str(pid)).mkdir()
        rest = " ".join(["0"] * 40)
        (tmp_path / str(pid) / "stat").write_text(f"{pid} ({comm}) {state} {ppid} {rest}\n")
    (tmp_path / "self").mkdir()
    return tmp_path


def test_stat_fields_survive_any_command_name(tmp_path: Path) -> None:
    proc = fake_proc(
        tmp_path, {10: ("a) b (c", "S", 1), 11: ("sdfrd", "Z", 10), 12: ("x", "R", 10)}
    )
    assert procfs.stat_fields(10, proc)[:2] == ["S", "1"]  # type: ignore[index]
    assert procfs.stat_fields(99, proc) is None
    assert procfs.running(10, proc) and procfs.running(12, proc)
    assert not procfs.running(11, proc) and not procfs.running(99, proc)
    kids = procfs.parent_map(proc)
    assert kids[1] == [10] and sorted(kids[10]) == [11, 12]
    assert procfs.tree(10, kids) == [10, 11, 12]


def test_this_process_is_running() -> None:
    assert procfs.running(os.getpid())
    assert os.getpid() in procfs.tree(os.getppid(), procfs.parent_map())
