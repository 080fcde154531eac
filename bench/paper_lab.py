"""What the paper bench and the side-by-side bench share around a lab: the machine's
conditions, process-tree sampling and captures."""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import subprocess
import threading
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import Any

from bench import err
from bench.paper_measure import Reading, usage
from netlab import capture, naming, procstat
from netlab.lab import Lab
from sdfr.host import procfs

ROOT = Path(__file__).resolve().parent.parent
SDFR_PORT = 1900
SAMPLE_EVERY_S = 2.0


def keep_logs(lab: Lab, folder: Path) -> None:
    """Each robot's daemon log into the run folder (the lab's own folder is short-lived: its
    path must stay short enough for the daemons' unix sockets)."""
    for name, robot in lab.robots.items():
        with contextlib.suppress(OSError):
            shutil.copyfile(robot.log, folder / f"sdfrd-{name}.log")


def run_folder_options(p: argparse.ArgumentParser) -> None:
    """The options of a bench that writes a run folder: the seed, where the folder goes, and a
    copy of the result JSON."""
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--runs", type=Path, default=ROOT / "runs", help="where the run folder goes")
    p.add_argument("--out", type=Path, help="also write the result JSON here")


def has_root(prog: str) -> bool:
    """Whether this process is root, as the labs' network namespaces need; says so if not."""
    if os.geteuid() != 0:
        err(f"{prog}: needs root (it runs robots in network namespaces)")
        return False
    return True


def conditions() -> dict[str, Any]:
    """The machine's state now: load averages and the busiest processes (the bench's CPU
    figures are only as good as the machine was quiet)."""
    load = os.getloadavg()
    try:
        top = subprocess.run(
            ["top", "-bn1", "-w", "200"], capture_output=True, text=True, timeout=10
        ).stdout.splitlines()
    except (OSError, subprocess.SubprocessError):
        top = []
    busiest = [line.strip() for line in top[7:12] if line.strip()]
    return {
        "time": datetime.now().isoformat(timespec="seconds"),
        "loadavg_1_5_15": [round(x, 2) for x in load],
        "top_processes": busiest,
    }


class Sampler:
    """Reads the CPU time and PSS of process trees every SAMPLE_EVERY_S seconds, in a thread."""

    def __init__(self, roots: dict[str, int]) -> None:
        self.roots = roots
        self.trees: dict[str, list[Reading]] = {name: [] for name in roots}
        self.layers: dict[str, dict[str, list[Reading]]] = {name: {} for name in roots}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def read(self) -> None:
        kids = procfs.parent_map()
        for name, root in self.roots.items():
            pids = procfs.tree(root, kids)
            u = procstat.Usage.read(pids)
            if u.processes:
                self.trees[name].append(Reading(u.time, u.cpu_s, u.pss_kb, u.rss_kb))
            for pid in pids:
                one = procstat.Usage.read([pid])
                if one.processes:
                    series = self.layers[name].setdefault(procstat.layer_of(pid), [])
                    series.append(Reading(one.time, one.cpu_s, one.pss_kb, one.rss_kb))
                # Layers that are threads of it (--layers threads): their CPU, by layer.
                for layer, tid in procstat.layer_threads(pid).items():
                    one = procstat.Usage.read_thread(pid, tid)
                    if one.processes:
                        series = self.layers[name].setdefault(layer, [])
                        series.append(Reading(one.time, one.cpu_s, one.pss_kb, one.rss_kb))

    def _run(self) -> None:
        while not self._stop.wait(SAMPLE_EVERY_S):
            self.read()

    def start(self) -> None:
        self.read()
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()
        self.read()

    def result(self) -> dict[str, Any]:
        return {
            name: {
                **usage(series),
                "layers": {layer: usage(s) for layer, s in sorted(self.layers[name].items())},
            }
            for name, series in self.trees.items()
        }


@contextlib.contextmanager
def captured(lab: Lab, folder: Path, bpf: str) -> Iterator[list[capture.Capture]]:
    caps = [
        capture.Capture(r.ns, naming.ROBOT_IFACE, folder / f"{name}.pcap", bpf=bpf)
        for name, r in lab.robots.items()
    ]
    capture.start_all(caps)
    try:
        yield caps
    finally:
        with contextlib.suppress(capture.CaptureError):
            capture.stop_all(caps)
