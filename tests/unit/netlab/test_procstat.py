"""netlab.procstat's readings of /proc, on a made-up /proc tree."""

from __future__ import annotations

import os
import threading
from pathlib import Path

from netlab import procstat


def _task(proc: Path, pid: int, tid: int, comm: str) -> None:
    task = proc / str(pid) / "task" / str(tid)
    task.mkdir(parents=True)
    (task / "comm").write_text(comm + "\n")


def test_threads_and_the_layer_threads_of_a_daemon(tmp_path: Path) -> None:
    _task(tmp_path, 10, 10, "python")
    _task(tmp_path, 10, 11, "sdfrd-api")
    _task(tmp_path, 10, 12, "sdfrd-discovery")
    _task(tmp_path, 10, 13, "worker")
    assert procstat.threads(10, tmp_path) == {
        10: "python",
        11: "sdfrd-api",
        12: "sdfrd-discovery",
        13: "worker",
    }
    assert procstat.layer_threads(10, tmp_path) == {"api": 11, "discovery": 12}
    assert procstat.threads(99, tmp_path) == {} and procstat.layer_threads(99, tmp_path) == {}


def test_threads_of_this_process() -> None:
    """The real /proc: a thread that names itself is seen under its name."""
    started, done = threading.Event(), threading.Event()

    def run() -> None:
        Path(f"/proc/self/task/{threading.get_native_id()}/comm").write_text("sdfrd-api")
        started.set()
        done.wait(5)

    t = threading.Thread(target=run)
    t.start()
    try:
        started.wait(5)
        assert t.native_id is not None
        assert procstat.threads(os.getpid())[t.native_id] == "sdfrd-api"
        assert procstat.layer_threads(os.getpid()) == {"api": t.native_id}
    finally:
        done.set()
        t.join()
