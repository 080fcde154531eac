"""Robots and their kinds: how a robot comes to have a network namespace, runs sdfrd, and runs
commands.

A lab works on each robot's *named* network namespace ``nl-<lab>-<robot>``: the medium links
it, shaping and captures run in it, and cleanup finds every process inside it.  A robot kind
(a "runtime") only decides how that namespace comes to be and how sdfrd runs there:

* ``namespace``: netlab makes the namespace; sdfrd runs as a host process inside it
  (``ip netns exec``), with the host's Python.
* ``docker``: the robot image (`compose/Dockerfile`, ``make image``).  A *robot container*
  ``nl-<lab>-<robot>`` runs with ``--network none`` and holds the robot's network namespace,
  its hostname and its filesystem, like a pod's first container; netlab gives its namespace
  the robot's name (a bind mount, as ``ip netns attach`` does, by the container's PID) and
  links it to the medium.  Each start of sdfrd is a *daemon container* ``nl-<lab>-<robot>.sdfrd``
  of the same image (its entrypoint, under ``--init``) in that namespace
  (``--network container:``), so a stop is a container's stop (SIGTERM to its init: sdfrd
  says Byebye), a kill its SIGKILL, and the robot's link, shaping and capture outlive a
  daemon restart, as a robot's radio outlives its software.  The state dir is the same host
  folder mounted at ``/var/lib/sdfr`` in both, so the lab reaches the daemon's API socket
  from the host, and registrations survive every restart.  ``exec`` runs in the robot
  container (its ``sdfr``).

Every container carries the lab's name as a label, and its name is in the lab's manifest
before it is created: `netlab down` removes them (see `netlab.cleanup`).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from ipaddress import IPv4Interface
from pathlib import Path
from typing import Any, ClassVar, Protocol

from netlab import docker, kernel, naming
from netlab.errors import kernel_errors
from sdfr.config.load import option_flags
from sdfr.daemon import MALLOC_TUNABLES, own_malloc_settings
from sdfr.host import procfs

RUNTIMES = ("namespace", "docker")
#: What robots meet on: a wired bridge, or 802.11 radios (mac80211_hwsim, the VM tier).
AIRS = ("wired", "radio")
#: A radio lab's medium: netlab's own (`netlab.airmedium`: the range model decides who hears a
#: frame) or hwsim's (the kernel's: every radio hears every other, no moves or partitions).
AIR_MEDIA = ("netlab", "hwsim")
#: Where a container robot's state dir is mounted (the image's volume).
CONTAINER_STATE_DIR = "/var/lib/sdfr"
#: sdfrd adds and removes its own addresses (`--addressing auto`): the daemon container
#: needs CAP_NET_ADMIN in its (the robot's) network namespace, and nothing else beyond
#: Docker's defaults (CAP_NET_RAW for its ARP probes is one of them).
DAEMON_CAPS = ("NET_ADMIN",)


@dataclass(frozen=True, slots=True)
class Robot:
    """One robot of a lab: its namespace, its link and where its daemon keeps its files."""

    name: str
    index: int
    ns: str
    port: str  # its port on the medium bridge
    mac: str
    address: IPv4Interface
    workdir: Path  # its daemon's state and log
    runtime: str = "namespace"
    #: Its link to the medium: eth0 (a veth to the bridge), or a radio's wlanN.
    iface: str = naming.ROBOT_IFACE

    @property
    def ip(self) -> str:
        return str(self.address.ip)

    @property
    def state_dir(self) -> Path:
        return self.workdir / "state"

    @property
    def log(self) -> Path:
        return self.workdir / "sdfrd.log"

    @property
    def api_socket(self) -> Path:
        return self.state_dir / "api.sock"

    @property
    def containers(self) -> tuple[str, ...]:
        """The containers of a docker robot: the robot's, then its daemon's; none otherwise."""
        if self.runtime != "docker":
            return ()
        return (self.ns, daemon_container(self.ns))


#: A robot by its name, or the robot.
RobotRef = str | Robot


def daemon_container(robot_container: str) -> str:
    """The name of a robot's daemon container ('.' is in no robot name: never another's)."""
    return f"{robot_container}.sdfrd"


class Daemon(Protocol):
    """A running sdfrd as the lab holds it (a `subprocess.Popen` is one)."""

    @property
    def pid(self) -> int: ...

    def poll(self) -> int | None: ...

    def wait(self, timeout: float | None = None) -> int: ...


@dataclass(slots=True)
class Started:
    """What a kind started for sdfrd: the daemon, the command (for the log and the manifest),
    and helper processes the lab stops with it (a container's log follower)."""

    daemon: Daemon
    argv: list[str]
    helpers: list[subprocess.Popen[bytes]] = field(default_factory=list)


def _header(log: Path, argv: Sequence[str]) -> None:
    with open(log, "ab") as out:
        out.write(f"--- netlab: {' '.join(argv)}\n".encode())


class RobotKind(ABC):
    """How robots of one kind get their namespace, run sdfrd and run commands."""

    runtime: ClassVar[str]

    @abstractmethod
    def create(self, lab: str, robot: Robot) -> None:
        """Make the robot's named network namespace `robot.ns` exist (empty: no eth0 yet)."""

    @abstractmethod
    def discard(self, lab: str, robot: Robot) -> None:
        """Remove what `create` made (a robot whose plumbing failed)."""

    @abstractmethod
    def spawn(self, lab: str, robot: Robot, options: Mapping[str, Any]) -> Started:
        """Start sdfrd with `options` (its flags by name), its output appended to `robot.log`."""

    @abstractmethod
    def exec_argv(self, robot: Robot, argv: Sequence[str], *, stdin: bool) -> list[str]:
        """`argv` run inside the robot (`stdin`: it reads standard input)."""


def daemon_env() -> dict[str, str] | None:
    """sdfrd's environment: netlab's, with glibc's malloc tunables sdfrd would set itself
    (`sdfr.daemon.pin_malloc`), sparing each daemon the exec that sets them: one interpreter
    start fewer per robot. None (netlab's own, unchanged) when the user set any of them."""
    if own_malloc_settings(os.environ):
        return None
    return {**os.environ, "GLIBC_TUNABLES": MALLOC_TUNABLES}


class NamespaceKind(RobotKind):
    """A namespace netlab makes; sdfrd as a host process inside it."""

    runtime = "namespace"

    def create(self, lab: str, robot: Robot) -> None:
        kernel.create_ns(robot.ns).close()

    def discard(self, lab: str, robot: Robot) -> None:
        kernel.remove_ns(robot.ns)  # its veth goes with it

    def argv(self, options: Mapping[str, Any]) -> list[str]:
        return [sys.executable, "-m", "sdfr.daemon", *option_flags(options)]

    def spawn(self, lab: str, robot: Robot, options: Mapping[str, Any]) -> Started:
        argv = self.argv(options)
        _header(robot.log, argv)
        with (
            open(robot.log, "ab") as log,
            kernel_errors(f"starting sdfrd in robot {robot.name}"),
        ):
            proc = subprocess.Popen(
                kernel.ns_argv(robot.ns, argv),
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
                env=daemon_env(),
            )
        return Started(proc, argv)

    def exec_argv(self, robot: Robot, argv: Sequence[str], *, stdin: bool) -> list[str]:
        return kernel.ns_argv(robot.ns, argv)


class ContainerDaemon:
    """sdfrd in its daemon container: `pid` is the container's init on the host.

    Like a Popen: `poll()` is None while it runs, then the container's exit status, with a
    signal as a negative number (Docker's 128+N, as Popen has -N).
    """

    def __init__(self, container: str, pid: int, follower: subprocess.Popen[bytes] | None):
        self.container = container
        self.pid = pid
        self._start = procfs.start_time(pid) if pid else None
        self._follower = follower
        self._code: int | None = None

    def poll(self) -> int | None:
        if self._code is not None:
            return self._code
        if self.pid and procfs.running(self.pid) and procfs.start_time(self.pid) == self._start:
            return None
        try:
            st = docker.wait_stopped(self.container)
        except docker.DockerError:
            st = None
        code = st.exit_code if st is not None else 137  # removed meanwhile: killed
        self._code = -(code - 128) if 128 < code < 160 else code
        if self._follower is not None:  # the end of its output is in the log
            try:
                self._follower.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self._follower.kill()
                self._follower.wait()
        return self._code

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            code = self.poll()
            if code is not None:
                return code
            if deadline is not None and time.monotonic() > deadline:
                raise subprocess.TimeoutExpired(self.container, timeout or 0.0)
            time.sleep(0.02)


class ContainerKind(RobotKind):
    """Robots as containers of `image` (see the module doc)."""

    runtime = "docker"

    def __init__(self, image: str = docker.DEFAULT_IMAGE) -> None:
        self.image = image

    def create(self, lab: str, robot: Robot) -> None:
        robot.state_dir.mkdir(parents=True, exist_ok=True)
        spec = docker.ContainerSpec(
            name=robot.ns,
            image=self.image,
            labels=docker.labels(lab, robot.name, "robot"),
            network="none",
            hostname=robot.name,
            entrypoint="sleep",
            argv=["infinity"],
            mounts={str(robot.state_dir): (CONTAINER_STATE_DIR, False)},
        )
        docker.run(spec)
        st = docker.state(robot.ns)
        if st is None or not st.running or not st.pid:
            raise docker.DockerError(f"the container {robot.ns} of robot {robot.name} stopped")
        kernel.attach_ns(robot.ns, st.pid)

    def discard(self, lab: str, robot: Robot) -> None:
        docker.remove(lab, robot.containers)
        kernel.remove_ns(robot.ns)

    def container_options(self, robot: Robot, options: Mapping[str, Any]) -> dict[str, Any]:
        """`options` as the daemon container sees them: its state dir is the image's volume."""
        return {**options, "state_dir": CONTAINER_STATE_DIR}

    @staticmethod
    def host_paths(options: Mapping[str, Any]) -> dict[str, tuple[str, bool]]:
        """Files the options name (a key file, a config): mounted read-only where they are."""
        out: dict[str, tuple[str, bool]] = {}
        for key, value in options.items():
            if key == "state_dir" or not isinstance(value, str | Path):
                continue
            path = str(value)
            if os.path.isabs(path) and os.path.exists(path):
                out[path] = (path, True)
        return out

    def spawn(self, lab: str, robot: Robot, options: Mapping[str, Any]) -> Started:
        name = daemon_container(robot.ns)
        docker.remove(lab, [name])  # the previous start's, stopped
        host_state = Path(options.get("state_dir") or robot.state_dir)
        opts = self.container_options(robot, options)
        spec = docker.ContainerSpec(
            name=name,
            image=self.image,
            labels=docker.labels(lab, robot.name, "sdfrd"),
            network=f"container:{robot.ns}",
            argv=option_flags(opts),
            env={"SDFR_ROBOT_ID": str(opts.get("robot_id") or robot.name)},
            mounts={
                str(host_state): (CONTAINER_STATE_DIR, False),
                **self.host_paths(options),
            },
            cap_add=DAEMON_CAPS,
        )
        argv = ["docker", "run", *spec.run_args()]
        _header(robot.log, argv)
        docker.run(spec)
        st = docker.state(name)
        pid = st.pid if st is not None and st.running else 0
        with open(robot.log, "ab") as log:
            follower = subprocess.Popen(
                docker.logs_argv(name),
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        return Started(ContainerDaemon(name, pid, follower), argv, [follower])

    def exec_argv(self, robot: Robot, argv: Sequence[str], *, stdin: bool) -> list[str]:
        return docker.exec_argv(robot.ns, argv, stdin=stdin)


def kind_for(runtime: str, image: str = docker.DEFAULT_IMAGE) -> RobotKind:
    if runtime == "namespace":
        return NamespaceKind()
    if runtime == "docker":
        return ContainerKind(image)
    raise ValueError(f"runtime: one of {', '.join(RUNTIMES)}, got {runtime!r}")
