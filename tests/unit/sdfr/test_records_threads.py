"""A service record decoded for the first time by several threads at once: the crash that
killed a robot's sdfrd with SIGSEGV (its API layer's first publish and its discovery layer's
first decode of a peer's services came at the same moment, inside msgspec's lazy build of the
type's decoding information; sdfr.records.model builds it at import)."""

from __future__ import annotations

import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

#: A fresh interpreter, switching threads as often as it can, eight threads released at once
#: into their first `Service.from_json`.  Before the fix, 2 runs in 40 died with SIGSEGV.
RACE = """
import sys, threading
sys.setswitchinterval(1e-6)
from sdfr.records.model import Service
barrier = threading.Barrier(8)
def go():
    barrier.wait()
    Service.from_json({"name": "cam", "type": "sensor.camera", "attributes": {"fps": 30}},
                      service_id="abc123")
threads = [threading.Thread(target=go) for _ in range(8)]
for t in threads:
    t.start()
for t in threads:
    t.join()
"""
RUNS = 48


def _run(_: int) -> int:
    done = subprocess.run([sys.executable, "-c", RACE], capture_output=True, timeout=60)
    return done.returncode


def test_the_first_decodes_of_a_service_in_many_threads_at_once_do_not_crash() -> None:
    with ThreadPoolExecutor(max_workers=4) as pool:
        codes = list(pool.map(_run, range(RUNS)))
    crashed = [c for c in codes if c != 0]
    assert not crashed, f"{len(crashed)} of {RUNS} interpreters died: exit statuses {crashed}"
