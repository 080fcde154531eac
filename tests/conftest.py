"""Shared test set-up: the ``root`` marker and the leak check.

* Tests marked ``@pytest.mark.root`` are skipped unless we are root and can
  create a network namespace here (CI runs as root, so there they run).
* The session fails if a test left behind a netlab namespace (``nl-*``) that
  did not exist when the session started, a lab's manifest, or a child
  process of pytest still running; what other processes (another lab, a
  concurrent session) made is not judged.  Leftovers are reported, then
  removed/killed by their exact name/pid, so a CI machine is left clean.
* Fleets are built with netlab itself: the fixtures of ``tests/support/fleets.py``.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import time
from collections.abc import Iterator
from typing import Any

import pytest
from pyroute2 import netns

from netlab import manifest, naming
from sdfr.host import procfs

pytest_plugins = ["tests.support.fleets", "tests.support.fakelab"]

_baseline_ns: set[str] = set()
_baseline_manifests: set[str] = set()
_baseline_host = False
_attributed: dict[str, str] = {}  # leftover (ns name or "pid N") -> first test after which seen
_leaks: list[str] = []  # filled at session finish, printed in the summary


def pytest_runtest_setup(item: pytest.Item) -> None:
    if item.get_closest_marker("root") is not None:
        from tests.support.fleets import need_root  # registered as a plugin above

        need_root()


# -- leak check -------------------------------------------------------------
NETLAB_PREFIX = naming.NS_PREFIX
NETLAB_MANIFESTS = manifest.run_dir()


def _sdfr_namespaces() -> set[str]:
    return {ns for ns in netns.listnetns() if ns.startswith(NETLAB_PREFIX)}


def _manifests() -> set[str]:
    """netlab labs still recorded as up (a lab that was not taken down); not the host-wide
    bookkeeping (`.host.json`), which is no lab's."""
    try:
        return {p.name for p in NETLAB_MANIFESTS.glob("*.json") if not p.name.startswith(".")}
    except OSError:
        return set()


def _lab_runner(ns: str) -> int | None:
    """The pid that runs the netlab lab owning `ns` (``nl-<lab>-...``), from its manifest."""
    lab = ns[len(NETLAB_PREFIX) :].split("-", 1)[0]
    try:
        data = json.loads((NETLAB_MANIFESTS / f"{lab}.json").read_text())
        return int(data.get("runner_pid", 0)) or None
    except (OSError, ValueError, AttributeError):
        return None


def _foreign(ns: str) -> bool:
    """A namespace of a lab run by another live process (another user's lab, a concurrent
    test session on the same machine) is not ours to judge.  Its runner says so while it runs;
    once it has exited (a lab brought up by `netlab up`), the name does: `unique_lab_name`
    puts the naming process's pid (modulo 36**4) in it, and a live process with that pid that
    is neither this one nor one of its descendants made it.  A namespace no lab records is
    judged as ours."""
    pid = _lab_runner(ns)
    if pid is None or pid == os.getpid():
        return False  # (no lab records it: whoever made it, it is left over)
    if os.path.exists(f"/proc/{pid}"):
        return True
    lab = ns[len(NETLAB_PREFIX) :].split("-", 1)[0]
    try:
        named_by = int(lab[1:5], 36) if len(lab) >= 6 else None
    except ValueError:
        named_by = None
    if named_by is None or named_by == os.getpid() % 36**4:
        return False
    return any(
        int(entry) % 36**4 == named_by and not _descends_from_us(int(entry))
        for entry in os.listdir("/proc")
        if entry.isdigit()
    )


def _descends_from_us(pid: int) -> bool:
    me = os.getpid()
    for _ in range(64):
        if pid == me:
            return True
        fields = procfs.stat_fields(pid)
        if not fields or len(fields) < 2 or not fields[1].isdigit() or int(fields[1]) <= 1:
            return False
        pid = int(fields[1])
    return False


def _new_namespaces() -> list[str]:
    return sorted(ns for ns in _sdfr_namespaces() - _baseline_ns if not _foreign(ns))


def _children() -> dict[int, str]:
    """Running (non-zombie) child processes of this pytest process."""
    me = os.getpid()
    out: dict[int, str] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        fields = procfs.stat_fields(int(entry))
        if not fields or fields[0] == "Z" or len(fields) < 2 or fields[1] != str(me):
            continue
        try:
            with open(f"/proc/{entry}/cmdline", "rb") as f:
                cmd = f.read().replace(b"\0", b" ").decode(errors="replace").strip()
        except (OSError, IndexError, ValueError):
            continue
        out[int(entry)] = cmd
    return out


def pytest_sessionstart(session: pytest.Session) -> None:
    global _baseline_host
    _baseline_ns.update(_sdfr_namespaces())
    _baseline_manifests.update(_manifests())
    _baseline_host = (NETLAB_MANIFESTS / ".host.json").exists()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    yield
    # Remember after which test a leftover was first seen, for the report.
    for ns in _new_namespaces():
        _attributed.setdefault(ns, item.nodeid)
    for pid in _children():
        _attributed.setdefault(f"pid {pid}", item.nodeid)


@pytest.hookimpl(tryfirst=True)
def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    deadline = time.monotonic() + 2.0
    # Under pytest-xdist the controller runs no test: its children are the workers, which
    # are still up here and check their own children.
    distributing = session.config.pluginmanager.hasplugin("dsession")
    children = {} if distributing else _children()
    while children and time.monotonic() < deadline:  # let exiting processes go
        time.sleep(0.05)
        children = _children()
    leaks = _leaks
    for pid, cmd in sorted(children.items()):
        where = _attributed.get(f"pid {pid}", "session teardown")
        leaks.append(f"child process {pid} still running ({cmd!r}), seen after {where}")
        try:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
        except (ProcessLookupError, ChildProcessError, PermissionError):
            pass
    for ns in _new_namespaces():
        where = _attributed.get(ns, "session teardown")
        leaks.append(f"network namespace {ns} left behind, seen after {where}")
        with contextlib.suppress(OSError):
            netns.remove(ns)
    left = _manifests()
    for record in sorted(left - _baseline_manifests):
        if _foreign(f"{NETLAB_PREFIX}{record.removesuffix('.json')}-air"):
            continue
        leaks.append(f"netlab lab manifest {NETLAB_MANIFESTS / record} left behind (lab not down)")
    # The raised ARP limits are put back by the last lab to go down: their bookkeeping
    # staying is right while any lab (another user's, too) is still up.
    host = NETLAB_MANIFESTS / ".host.json"
    if host.exists() and not _baseline_host and not left:
        leaks.append(f"{host} left behind: the host's ARP limits were not put back")
    if hasattr(session.config, "workerinput"):  # a pytest-xdist worker: tell the controller
        session.config.workeroutput["sdfr_leaks"] = list(leaks)  # type: ignore[attr-defined]
    if leaks and session.exitstatus in (pytest.ExitCode.OK, pytest.ExitCode.NO_TESTS_COLLECTED):
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node: Any, error: object) -> None:
    """A pytest-xdist worker is done: its leaks are the session's."""
    worker = getattr(node, "gateway", None)
    for line in getattr(node, "workeroutput", {}).get("sdfr_leaks", []):
        _leaks.append(f"{getattr(worker, 'id', 'a worker')}: {line}")


def pytest_terminal_summary(terminalreporter: Any, exitstatus: int, config: pytest.Config) -> None:
    if _leaks:
        terminalreporter.section("leaked resources (session fails)", sep="=", red=True)
        for line in _leaks:
            terminalreporter.write_line(line, red=True)
