"""pytest fixtures for netlab labs (a plugin of tests/conftest.py).

* ``lab``: a fresh `Lab`, up, with a name unique on this machine; taken down after the test
  even when it failed, tolerating what the test already removed (robots, namespaces, the lab
  itself).  Teardown fails the test if anything of the lab is left.
* ``lab_factory(**lab_kw)``: as many such labs as a test needs.
* ``fleet``: a lab with robots r1..rN running sdfrd, set with
  ``@pytest.mark.fleet(n=3, beacon=0.5, ...)`` (defaults: 3 robots, beacon 0.5 s; other
  keywords go to `fleet_factory`).
* ``fleet_factory(n=3, *, beacon=0.5, spacing=1.0, start=True, **lab_kw)``: fleets on demand.
* ``captured(lab, name)``: a context manager capturing every robot of `lab` and its medium;
  when the block fails, the pcaps are kept under runs/tests/ (the failure says where).
* When a test (or its set-up) fails, the folders of the labs it made (daemon logs, state) are
  copied, before the labs go down, to ``$SDFR_KEEP_LOGS/<test>-<time>-<pid>/<lab>/`` (default
  runs/tests/), and the failure report gains a "daemon logs" section saying where.

Each skips the test unless we are root (the ``root`` marker does it too).
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import stat
import subprocess
from collections.abc import Callable, Generator, Iterator
from datetime import datetime
from functools import cache
from pathlib import Path
from typing import Any

import pytest
from pyroute2 import netns

from netlab import cleanup, kernel, manifest, naming
from netlab.capture import Capture, start_all, stop_all
from netlab.lab import Lab

#: Where a failed test's captures are kept.
RUNS = Path(__file__).resolve().parents[2] / "runs" / "tests"


def run_folder(name: str) -> Path:
    """A new folder name under RUNS for a test's run called `name`."""
    return RUNS / f"{name}-{datetime.now():%Y%m%d-%H%M%S}-{os.getpid()}"


def keep_folder(test: str) -> Path:
    """Where a failed test's lab folders are kept: under $SDFR_KEEP_LOGS, else RUNS."""
    base = os.environ.get("SDFR_KEEP_LOGS")
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", test).strip("_")[:80]
    if not base:
        return run_folder(name)
    return Path(base).absolute() / f"{name}-{datetime.now():%Y%m%d-%H%M%S}-{os.getpid()}"


def _not_files(folder: str, names: list[str]) -> list[str]:
    """copytree's ignore: sockets, fifos and devices (a daemon's api.sock) are not copied."""
    out = []
    for name in names:
        try:
            mode = os.lstat(os.path.join(folder, name)).st_mode
        except OSError:
            out.append(name)
            continue
        if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
            out.append(name)
    return out


def keep_lab_folders(labs: list[Lab], folder: Path) -> list[str]:
    """Copy each lab's folder (its robots' daemon logs and state) into `folder`/<lab>; one line
    per lab saying where it went, or why it could not."""
    lines = []
    for lab in labs:
        src = lab.workdir
        if not str(src) or src == Path() or not src.is_dir():
            lines.append(f"lab {lab.name}: no folder to keep ({src or 'not up'})")
            continue
        dest = folder / lab.name
        try:
            shutil.copytree(src, dest, ignore=_not_files, dirs_exist_ok=True)
        except (shutil.Error, OSError) as exc:  # a log the daemon was still writing: keep the rest
            lines.append(f"lab {lab.name}: some files not copied ({str(exc)[:200]})")
        logs = sorted(p.relative_to(dest).as_posix() for p in dest.glob("*/sdfrd.log"))
        lines.append(f"lab {lab.name}: daemon logs kept in {dest} ({', '.join(logs) or 'none'})")
    return lines


#: The labs a test made (lab_factory), for the failure report.
LABS = pytest.StashKey[list[Lab]]()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(
    item: pytest.Item, call: pytest.CallInfo[None]
) -> Generator[None, Any, None]:
    outcome = yield
    report = outcome.get_result()
    labs = item.stash.get(LABS, [])
    if not (report.failed and labs) or report.when == "teardown":
        return
    lines = keep_lab_folders(labs, keep_folder(item.nodeid.split("/")[-1]))
    item.stash[LABS] = []  # kept once: a failed set-up has no call
    report.sections.append(("daemon logs", "\n".join(lines)))


def discard(folder: Path) -> None:
    """Remove a passed run's folder, unless SDFR_KEEP_RUNS=1 asks to keep every run."""
    if os.environ.get("SDFR_KEEP_RUNS") != "1":
        shutil.rmtree(folder, ignore_errors=True)


DEFAULT_ROBOTS = 3
DEFAULT_BEACON = 0.5
ROOT_SKIP_REASON = "needs root and network namespaces (CI runs as root)"


@cache
def netns_usable() -> bool:
    """Root, `ip netns` works, and a namespace can really be created."""
    if os.geteuid() != 0 or shutil.which("ip") is None:
        return False
    try:
        ok = subprocess.run(
            ["ip", "netns", "list"], capture_output=True, timeout=10, stdin=subprocess.DEVNULL
        )
    except (OSError, subprocess.SubprocessError):
        return False
    if ok.returncode != 0:
        return False
    probe = f"{naming.NS_PREFIX}{unique_lab_name()}-probe"
    try:
        netns.create(probe)
    except Exception:
        return False
    finally:
        if probe in netns.listnetns():
            netns.remove(probe)
    return True


def need_root() -> None:
    """Skip the test unless it can make network namespaces."""
    if not netns_usable():
        pytest.skip(ROOT_SKIP_REASON)


def unique_lab_name() -> str:
    """A lab name unique on this machine ('f' + this process + a counter); names whose
    namespaces exist are skipped."""
    taken = kernel.list_ns(naming.NS_PREFIX) if os.geteuid() == 0 else []
    return naming.unique_lab_name("f", taken)


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "fleet(n=3, beacon=0.5, **kw): robots and sdfrd options of the `fleet` fixture",
    )


def _take_down(lab: Lab) -> list[str]:
    """Take `lab` down whatever state it is in; what is left of it (empty when nothing)."""
    problems: list[str] = []
    try:
        lab.down()
    except Exception as exc:  # report it, then sweep by name below
        problems.append(f"{lab.name}: down() failed: {exc}")
    if cleanup.leftovers(lab.name):
        try:
            cleanup.sweep(lab.name, manifest.load(lab.name))
        except Exception as exc:
            problems.append(f"{lab.name}: sweep failed: {exc}")
    left = cleanup.leftovers(lab.name)
    if left:
        problems.append(f"{lab.name}: left behind: {', '.join(left)}")
    return problems


@pytest.fixture
def lab_factory(request: pytest.FixtureRequest) -> Iterator[Callable[..., Lab]]:
    """``make(**lab_kw) -> Lab``: up, uniquely named; every one is taken down after the test
    (its folder kept first when the test failed: see the module doc)."""
    need_root()
    labs: list[Lab] = []
    request.node.stash[LABS] = labs

    def make(**kw: Any) -> Lab:
        lab = Lab(unique_lab_name(), **kw)
        labs.append(lab)
        return lab.up()

    yield make
    problems = [p for lab in reversed(labs) for p in _take_down(lab)]
    if problems:
        pytest.fail("lab teardown: " + "; ".join(problems))


@pytest.fixture
def lab(lab_factory: Callable[..., Lab]) -> Lab:
    """A fresh lab with no robots yet."""
    return lab_factory()


@pytest.fixture
def fleet_factory(lab_factory: Callable[..., Lab]) -> Callable[..., Lab]:
    """``make(n=3, *, beacon=0.5, spacing=1.0, start=True, options=None, **lab_kw) -> Lab``:
    robots r1..rn standing `spacing` metres apart on a line, running sdfrd (unless not
    `start`) with that beacon and more sdfrd `options`."""

    def make(
        n: int = DEFAULT_ROBOTS,
        *,
        beacon: float = DEFAULT_BEACON,
        spacing: float = 1.0,
        start: bool = True,
        options: dict[str, Any] | None = None,
        **lab_kw: Any,
    ) -> Lab:
        lab = lab_factory(**lab_kw)
        names = [f"r{i}" for i in range(1, n + 1)]
        lab.add_robots(names, {name: (i * spacing, 0.0) for i, name in enumerate(names)})
        if start:
            lab.start_all(timeout=max(60.0, 2.0 * n), beacon_interval=beacon, **(options or {}))
        return lab

    return make


@pytest.fixture
def fleet(request: pytest.FixtureRequest, fleet_factory: Callable[..., Lab]) -> Lab:
    """A lab with robots running sdfrd; ``@pytest.mark.fleet(n=..., beacon=...)`` sets them."""
    marker = request.node.get_closest_marker("fleet")
    if marker is not None and marker.args:
        raise TypeError("write @pytest.mark.fleet(n=3, beacon=0.5) with keywords")
    return fleet_factory(**(marker.kwargs if marker is not None else {}))


@contextlib.contextmanager
def captured(lab: Lab, name: str) -> Iterator[Path]:
    """tcpdump on every robot of `lab` (added so far) and on its medium while the block runs;
    the pcaps are removed when it passes (unless SDFR_KEEP_RUNS=1) and kept, with the daemons'
    logs, when it fails -- the failure's message gains the folder."""
    folder = run_folder(name)
    folder.mkdir(parents=True, exist_ok=True)
    caps = [Capture(lab.medium.ns, naming.BRIDGE, folder / "medium.pcap", label="medium")]
    caps += [
        Capture(r.ns, naming.ROBOT_IFACE, folder / f"{r.name}.pcap", label=r.name)
        for r in lab.robots.values()
    ]
    start_all(caps)
    try:
        yield folder
    except BaseException as exc:
        with contextlib.suppress(Exception):
            stop_all(caps)
        for r in lab.robots.values():
            with contextlib.suppress(OSError):
                shutil.copyfile(r.log, folder / f"{r.name}.log")
        note = f"pcaps and daemon logs kept for inspection in {folder}"
        if isinstance(exc, pytest.fail.Exception):
            raise pytest.fail.Exception(f"{exc.msg}\n{note}", pytrace=exc.pytrace) from None
        print(note)
        raise
    stop_all(caps)
    discard(folder)
