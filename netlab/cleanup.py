"""Taking a lab down: its processes, its namespaces, its workdir and its manifest.

Used by `Lab.down()` and by `netlab down NAME` after the runner died, so
both remove the same things the same way:

1. every recorded process that is still ours (inside one of the lab's
   namespaces, or with the recorded start time, so a reused pid is never
   hit) gets SIGTERM (its process group: sdfrd says Byebye), then SIGKILL
   after a grace period;
2. its containers (robots of the docker runtime) are removed: those the
   manifest records and any labelled with the lab's name;
3. anything still running inside the lab's namespaces is ours by
   definition and is killed by pid (a radio robot's wpa_supplicant too);
4. its radios (a radio lab's) are brought back from the robots' namespaces and removed,
   and any left in the initial namespace named like the lab's namespaces;
5. the namespaces are deleted, recorded ones and any named ``nl-<lab>-*``;
   the bridge, veths, nft table and qdiscs go with them;
6. a workdir the lab made itself is removed (unless `keep_workdir`: `netlab down`
   keeps the daemons' logs and state unless asked), then the manifest; the last
   lab to go puts back the host's ARP table limits (`netlab.hostlimits`).

Nothing is matched by process name or command line.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from netlab import docker, hostlimits, hwsim, kernel, manifest, naming
from netlab.errors import KernelError, NetlabError
from netlab.manifest import Manifest, ProcRecord
from sdfr.host import procfs

TERM_GRACE = 5.0
KILL_WAIT = 5.0


start_time = procfs.start_time
running = procfs.running


def netns_of(pid: int) -> tuple[int, int] | None:
    try:
        st = os.stat(f"/proc/{pid}/ns/net")
    except OSError:
        return None
    return (st.st_dev, st.st_ino)


def is_ours(rec: ProcRecord, inodes: set[tuple[int, int]]) -> bool:
    """The recorded process is alive and still the one we started."""
    if not running(rec.pid):
        return False
    return netns_of(rec.pid) in inodes or start_time(rec.pid) == rec.start


def pids_inside(inodes: set[tuple[int, int]]) -> list[int]:
    """Every live process whose network namespace is one of `inodes` (never ourselves)."""
    me = os.getpid()
    out: list[int] = []
    for entry in os.listdir("/proc"):
        pid = int(entry) if entry.isdigit() else me
        if pid != me and netns_of(pid) in inodes and running(pid):
            out.append(pid)
    return out


def signal_process(pid: int, sig: int) -> None:
    """`sig` to the process group `pid` leads (lab processes have a session each), else to `pid`."""
    with contextlib.suppress(ProcessLookupError, PermissionError):
        if os.getpgid(pid) == pid:
            os.killpg(pid, sig)
        else:
            os.kill(pid, sig)


def wait_gone(pids: Iterable[int], timeout: float) -> list[int]:
    """Wait until none of `pids` runs; those still running at the deadline."""
    left = [p for p in pids if running(p)]
    deadline = time.monotonic() + timeout
    while left and time.monotonic() < deadline:
        time.sleep(0.02)
        left = [p for p in left if running(p)]
    return left


def stop_processes(
    records: Iterable[ProcRecord], inodes: set[tuple[int, int]], grace: float
) -> list[int]:
    """SIGTERM, then SIGKILL after `grace`, to each recorded process that is still ours."""
    ours = [r.pid for r in records if is_ours(r, inodes)]
    for pid in ours:
        signal_process(pid, signal.SIGTERM)
    for pid in wait_gone(ours, grace):
        signal_process(pid, signal.SIGKILL)
    return ours


def kill_inside(inodes: set[tuple[int, int]]) -> list[int]:
    """SIGKILL whatever still runs inside the namespaces; the pids killed."""
    killed: list[int] = []
    for _ in range(3):  # a dying parent may still fork: look again
        pids = pids_inside(inodes)
        if not pids:
            break
        for pid in pids:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, signal.SIGKILL)
        killed += pids
        wait_gone(pids, KILL_WAIT)
    return killed


@dataclass(slots=True)
class SweepResult:
    processes: list[int] = field(default_factory=list)
    namespaces: list[str] = field(default_factory=list)
    containers: list[str] = field(default_factory=list)
    radios: list[str] = field(default_factory=list)
    workdir: str | None = None  # the workdir removed
    kept: str | None = None  # the workdir left in place (`keep_workdir`, or not the lab's own)
    manifest: bool = False

    @property
    def empty(self) -> bool:
        return not (
            self.processes
            or self.namespaces
            or self.containers
            or self.radios
            or self.workdir
            or self.manifest
        )


def remove_radios(name: str, record: Manifest | None, namespaces: Iterable[str]) -> list[str]:
    """Remove the lab's radios: the recorded ones (brought back from their robots'
    namespaces first) and any in this namespace named with the lab's prefix.  hwsim is not
    asked when it is not loaded and the manifest records no radio (a wired lab)."""
    recorded = {r.radio: r.ns for r in record.robots.values() if r.radio} if record else {}
    if not recorded and not hwsim.loaded():
        return []
    live = set(namespaces)
    removed: list[str] = []
    with hwsim.Hwsim() as hw:
        for radio, ns in recorded.items():
            if hwsim.release(hw, radio, ns if ns in live else None):
                removed.append(radio)
        for left in hw.radios():
            if left.name.startswith(naming.prefix(name)) and hw.remove_radio(left.name):
                removed.append(left.name)
    return removed


def remove_containers(name: str, record: Manifest | None) -> list[str]:
    """Remove the lab's containers: the recorded ones and any labelled with its name.

    Docker is not asked about a lab whose manifest records none (a namespace lab); without a
    manifest it is asked if it answers.  KernelError if containers are recorded and Docker
    does not answer (they cannot be removed now: the manifest stays for another try).
    """
    recorded = list(record.containers) if record is not None else []
    if record is not None and not recorded:
        return []
    reason = docker.why_not()
    if reason is not None:
        if recorded:
            raise KernelError(
                f"its containers ({', '.join(recorded)}) cannot be removed: {reason}; "
                f"`netlab down {name}` again once Docker runs"
            )
        return []
    try:
        return docker.remove(name)
    except docker.DockerError as exc:
        raise KernelError(str(exc)) from None


def leftovers(name: str) -> list[str]:
    """What of lab `name` is still there: its namespaces, its containers (when Docker
    answers) and its manifest (as text); empty once the lab is down."""
    left = [f"namespace {ns}" for ns in kernel.list_ns(naming.prefix(name))]
    with contextlib.suppress(docker.DockerError):  # no Docker here: no containers either
        left += [f"container {c}" for c in docker.labelled(name)]
    if manifest.load(name) is not None:
        left.append(f"manifest {manifest.path_of(name)}")
    return left


def sweep(
    name: str, record: Manifest | None, grace: float = TERM_GRACE, *, keep_workdir: bool = False
) -> SweepResult:
    """Remove everything of lab `name` (see the module doc); KernelError if something stays."""
    naming.check_lab_name(name)
    result = SweepResult()
    recorded = record.namespaces if record is not None else []
    namespaces = sorted(
        {ns for ns in recorded if ns in kernel.list_ns()} | set(kernel.list_ns(naming.prefix(name)))
    )
    inodes = {i for i in (kernel.ns_inode(ns) for ns in namespaces) if i is not None}
    if record is not None:
        result.processes += stop_processes(record.processes, inodes, grace)
    errors: list[str] = []
    try:
        result.containers = remove_containers(name, record)
    except KernelError as exc:
        errors.append(str(exc))
    if inodes:
        result.processes += [p for p in kill_inside(inodes) if p not in result.processes]
    left = pids_inside(inodes) if inodes else []
    if left:
        errors.append(f"processes {left} inside the lab's namespaces did not die")
    try:
        result.radios = remove_radios(name, record, namespaces)
    except NetlabError as exc:
        errors.append(str(exc))
    for ns in namespaces:
        try:
            if kernel.remove_ns(ns):
                result.namespaces.append(ns)
        except KernelError as exc:
            errors.append(str(exc))
    if errors:
        # The manifest stays, so that another `netlab down` can finish the job.
        raise KernelError(f"lab {name}: " + "; ".join(errors))
    workdir = record.workdir if record is not None else ""
    if workdir and Path(workdir).exists():
        if record is not None and record.workdir_owned and not keep_workdir:
            shutil.rmtree(workdir, ignore_errors=True)
            result.workdir = workdir
        else:
            result.kept = workdir
    result.manifest = manifest.remove(name)
    hostlimits.restore_if_last()
    return result
