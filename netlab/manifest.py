"""The record of what a lab created: ``/run/netlab/<lab>.json``.

Written when the lab comes up (created exclusively: that is how a lab
claims its name), rewritten atomically as robots and processes are added,
and removed when the lab is taken down. `netlab down` reads it to sweep a
lab whose runner died. /run is a tmpfs, so a reboot (which also clears
every namespace) clears the manifests too.

``NETLAB_RUN_DIR`` overrides the directory (unit tests without root).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from netlab.errors import KernelError, LabExistsError, NetlabError, describe, kernel_errors

VERSION = 1


def run_dir() -> Path:
    return Path(os.environ.get("NETLAB_RUN_DIR", "/run/netlab"))


def path_of(name: str) -> Path:
    return run_dir() / f"{name}.json"


@dataclass(slots=True)
class RobotRecord:
    index: int
    ns: str
    port: str
    mac: str
    address: str  # with prefix length, e.g. 10.1.0.1/16
    runtime: str = "namespace"  # or "docker": its containers are named after `ns`
    iface: str = "eth0"  # its link: eth0, or its radio's interface
    radio: str = ""  # the name of its hwsim radio (a radio lab), made after it is recorded


@dataclass(slots=True)
class ProcRecord:
    """A process the lab started; `start` (clock ticks since boot) tells it from a pid reuse."""

    pid: int
    start: int
    robot: str
    role: str  # "sdfrd", "process", or "log" (a container's log follower)
    argv: list[str]


@dataclass(slots=True)
class Manifest:
    name: str
    seed: int = 0
    fleet: int = 1
    workdir: str = ""
    workdir_owned: bool = False
    runner_pid: int = 0
    runner_start: int = 0
    created: float = field(default_factory=time.time)
    runtime: str = "namespace"  # the lab's default robot kind
    image: str = ""  # the robot image of docker robots
    addressing: str = "manual"
    #: "wired" (a bridge) or "radio" (hwsim radios, one per robot)
    air: str = "wired"
    #: Left running by its runner (`netlab up`): a missing runner is no failure, and other
    #: processes may change its medium (`netlab partition`...), from `medium`.
    detached: bool = False
    #: The medium's state when detached: `Topology.to_json()` plus "shapes" (robot -> its
    #: `LinkShape` parameters).
    medium: dict[str, Any] = field(default_factory=dict)
    namespaces: list[str] = field(default_factory=list)
    robots: dict[str, RobotRecord] = field(default_factory=dict)
    processes: list[ProcRecord] = field(default_factory=list)
    #: Every container of the lab, recorded before it is created.
    containers: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, object]:
        return {"version": VERSION, **asdict(self)}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Manifest:
        try:
            return cls(
                name=str(data["name"]),
                seed=int(data.get("seed", 0)),
                fleet=int(data.get("fleet", 1)),
                workdir=str(data.get("workdir", "")),
                workdir_owned=bool(data.get("workdir_owned", False)),
                runner_pid=int(data.get("runner_pid", 0)),
                runner_start=int(data.get("runner_start", 0)),
                created=float(data.get("created", 0.0)),
                runtime=str(data.get("runtime", "namespace")),
                image=str(data.get("image", "")),
                addressing=str(data.get("addressing", "manual")),
                air=str(data.get("air", "wired")),
                detached=bool(data.get("detached", False)),
                medium=dict(data.get("medium") or {}),
                namespaces=[str(n) for n in data.get("namespaces", [])],
                robots={str(k): RobotRecord(**v) for k, v in dict(data.get("robots", {})).items()},
                processes=[ProcRecord(**p) for p in data.get("processes", [])],
                containers=[str(c) for c in data.get("containers", [])],
            )
        except (KeyError, TypeError, ValueError) as exc:
            what = f"missing field {exc}" if isinstance(exc, KeyError) else str(exc)
            raise NetlabError(
                f"lab manifest {path_of(str(data.get('name', '?')))} is unreadable ({what}): "
                "`netlab down NAME` sweeps the lab by its name"
            ) from None


def claim(manifest: Manifest) -> Path:
    """Create the manifest, or raise LabExistsError if a lab of that name is up.

    The whole file is written under a private name first and then hard-linked into
    place: the link fails if the name is taken, and a reader (another lab counting
    its neighbours, `netlab status`) never sees an empty or half-written manifest.
    """
    path = path_of(manifest.name)
    with kernel_errors(f"creating {run_dir()}"):
        run_dir().mkdir(parents=True, exist_ok=True)
    tmp = _private(path)
    try:
        with kernel_errors(f"writing {tmp}"):
            tmp.write_text(json.dumps(manifest.to_json(), indent=1))
            tmp.chmod(0o644)
        try:
            os.link(tmp, path)
        except FileExistsError:
            raise LabExistsError(
                f"lab {manifest.name!r} is already up (manifest {path}); `netlab status "
                f"{manifest.name}` shows it, `netlab down {manifest.name}` removes it"
            ) from None
        except OSError as exc:
            raise KernelError(describe(exc, f"creating {path}"), exc.errno) from exc
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
    return path


def _private(path: Path) -> Path:
    """A name no other writer uses (process and thread), hidden from names()."""
    return path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")


def save(manifest: Manifest) -> None:
    """Replace the manifest atomically (a reader never sees half a file)."""
    path = path_of(manifest.name)
    tmp = _private(path)
    with kernel_errors(f"writing {path}"):
        tmp.write_text(json.dumps(manifest.to_json(), indent=1))
        tmp.replace(path)


def load(name: str) -> Manifest | None:
    """The manifest of lab `name`, or None if there is none."""
    try:
        text = path_of(name).read_text()
    except FileNotFoundError:
        return None
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise NetlabError(f"lab manifest {path_of(name)} is not JSON ({exc}); remove it") from None
    if not isinstance(data, dict):
        raise NetlabError(f"lab manifest {path_of(name)} is not a JSON object; remove it")
    return Manifest.from_json(data)


def remove(name: str) -> bool:
    with contextlib.suppress(FileNotFoundError):
        (run_dir() / f".{name}.lock").unlink()
    try:
        path_of(name).unlink()
    except FileNotFoundError:
        return False
    return True


@contextlib.contextmanager
def locked(name: str) -> Iterator[None]:
    """Hold lab `name`'s lock: one process at a time changes a detached lab."""
    with kernel_errors(f"creating {run_dir()}"):
        run_dir().mkdir(parents=True, exist_ok=True)
    path = run_dir() / f".{name}.lock"
    with kernel_errors(f"locking {path}"), open(path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def names() -> list[str]:
    """Names of the labs that have a manifest."""
    with contextlib.suppress(FileNotFoundError):
        return sorted(p.stem for p in run_dir().glob("*.json") if not p.name.startswith("."))
    return []


def others(name: str) -> list[Manifest]:
    """The readable manifests of labs other than `name`.

    Another lab's record is not ours to judge: one that is gone or damaged by the
    time it is read is left out (`netlab status` names a damaged one), never an error here.
    """
    found = []
    for other in names():
        if other == name:
            continue
        with contextlib.suppress(NetlabError):
            record = load(other)
            if record is not None:
                found.append(record)
    return found
