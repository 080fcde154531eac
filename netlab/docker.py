"""Docker plumbing for container robots: the only code in netlab that runs `docker`.

Every container netlab makes carries the labels ``netlab.lab=<lab>``, ``netlab.robot=<robot>``
and ``netlab.role=robot|sdfrd``, so `netlab down` finds a lab's containers by label even when
the runner died before it could record them.  Errors come out as DockerError, saying what
failed, Docker's own words, and what to do.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from netlab.errors import NetlabError

#: The robot image `make image` builds (compose/Dockerfile).
DEFAULT_IMAGE = "sdfr-robot:latest"
LAB_LABEL = "netlab.lab"
ROBOT_LABEL = "netlab.robot"
ROLE_LABEL = "netlab.role"
TIMEOUT = 120.0


class DockerError(NetlabError):
    """Docker is missing or not running, or a docker command failed; the message says which."""


def binary() -> str:
    found = shutil.which("docker")
    if found is None:
        raise DockerError(
            "docker: command not found; container robots need Docker's engine "
            "(`make image` installs and starts it: scripts/docker-up.sh)"
        )
    return found


def docker(args: Sequence[str], doing: str, *, timeout: float = TIMEOUT) -> str:
    """Run `docker ARGS` to completion; its stdout, or DockerError with its stderr."""
    argv = [binary(), *args]
    try:
        res = subprocess.run(
            argv, capture_output=True, text=True, timeout=timeout, stdin=subprocess.DEVNULL
        )
    except subprocess.TimeoutExpired:
        raise DockerError(f"{doing}: docker did not answer within {timeout:g} s") from None
    except OSError as exc:
        raise DockerError(f"{doing}: cannot run docker: {exc.strerror}") from None
    if res.returncode != 0:
        said = " ".join(res.stderr.split())[:400] or f"exit status {res.returncode}"
        raise DockerError(f"{doing} failed: {said}{_hint(said)}")
    return res.stdout


def _hint(said: str) -> str:
    if "Cannot connect to the Docker daemon" in said or "Is the docker daemon running" in said:
        return " (start Docker's engine: scripts/docker-up.sh starts one)"
    if "No such image" in said or "Unable to find image" in said:
        return " (`make image` builds the robot image)"
    return ""


def why_not() -> str | None:
    """None when Docker's engine answers here; else why not, in words a user can act on."""
    try:
        docker(["version", "--format", "{{.Server.Version}}"], "asking Docker's engine", timeout=20)
    except DockerError as exc:
        return str(exc)
    return None


def require_image(image: str) -> None:
    """DockerError unless Docker answers and has `image` (netlab never pulls one)."""
    reason = why_not()
    if reason is not None:
        raise DockerError(f"container robots need Docker: {reason}")
    try:
        docker(["image", "inspect", "--format", "{{.Id}}", image], f"looking up image {image}")
    except DockerError:
        raise DockerError(
            f"no image {image} here: `make image` builds sdfr-robot from this checkout"
        ) from None


def labels(lab: str, robot: str, role: str) -> dict[str, str]:
    return {LAB_LABEL: lab, ROBOT_LABEL: robot, ROLE_LABEL: role}


@dataclass(frozen=True, slots=True)
class ContainerSpec:
    """What `docker run -d` is given; `argv` follows the image (its entrypoint's arguments)."""

    name: str
    image: str
    labels: Mapping[str, str]
    network: str = "none"
    hostname: str | None = None
    entrypoint: str | None = None
    argv: Sequence[str] = ()
    env: Mapping[str, str] = field(default_factory=dict)
    #: host path -> (container path, read-only)
    mounts: Mapping[str, tuple[str, bool]] = field(default_factory=dict)
    cap_add: Sequence[str] = ()

    def run_args(self) -> list[str]:
        """The arguments of `docker run`, after `run`."""
        args = ["-d", "--name", self.name, "--init", "--network", self.network]
        for key, value in sorted(dict(self.labels).items()):
            args += ["--label", f"{key}={value}"]
        if self.hostname is not None:
            args += ["--hostname", self.hostname]
        for cap in self.cap_add:
            args += ["--cap-add", cap]
        for key, value in sorted(dict(self.env).items()):
            args += ["--env", f"{key}={value}"]
        for host, (inside, ro) in sorted(dict(self.mounts).items()):
            args += ["--volume", f"{host}:{inside}{':ro' if ro else ''}"]
        if self.entrypoint is not None:
            args += ["--entrypoint", self.entrypoint]
        return [*args, self.image, *self.argv]


def run(spec: ContainerSpec) -> str:
    """Start the container; its id."""
    out = docker(["run", *spec.run_args()], f"starting container {spec.name}")
    return out.strip()


@dataclass(frozen=True, slots=True)
class State:
    running: bool
    pid: int  # on the host; 0 when not running
    exit_code: int
    status: str  # created, running, exited, ...


def state(name: str) -> State | None:
    """The container's state, or None if there is no container of that name."""
    try:
        out = docker(
            ["container", "inspect", "--format", "{{json .State}}", name],
            f"inspecting container {name}",
        )
    except DockerError as exc:
        if "No such container" in str(exc) or "No such object" in str(exc):
            return None
        raise
    data = json.loads(out)
    return State(
        bool(data.get("Running")),
        int(data.get("Pid") or 0),
        int(data.get("ExitCode") or 0),
        str(data.get("Status", "")),
    )


def wait_stopped(name: str, timeout: float = 10.0) -> State | None:
    """Docker's view once it has noticed the container's end (it reaps asynchronously)."""
    deadline = time.monotonic() + timeout
    while True:
        st = state(name)
        if st is None or not st.running or time.monotonic() > deadline:
            return st
        time.sleep(0.02)


def labelled(lab: str) -> list[str]:
    """The names of every container (running or not) labelled as lab `lab`'s."""
    out = docker(
        ["ps", "-a", "--filter", f"label={LAB_LABEL}={lab}", "--format", "{{.Names}}"],
        f"listing the containers of lab {lab}",
    )
    return sorted(line.strip() for line in out.splitlines() if line.strip())


def remove(lab: str, names: Sequence[str] | None = None) -> list[str]:
    """Force-remove lab `lab`'s containers (and their anonymous volumes): those of `names`,
    or all.  A container is the lab's by its label, never by its name alone: one of the same
    name made by someone else is left alone.  The names of those removed."""
    there = [n for n in labelled(lab) if names is None or n in names]
    if there:
        docker(["rm", "-f", "-v", *there], f"removing containers {', '.join(there)}")
    return there


def exec_argv(container: str, argv: Sequence[str], *, stdin: bool, tty: bool = False) -> list[str]:
    """`argv` run inside the container with `docker exec`."""
    if isinstance(argv, str):
        raise TypeError("argv must be a sequence of strings, not a string")
    flags = (["-i"] if stdin else []) + (["-t"] if tty else [])
    return [binary(), "exec", *flags, container, *argv]


def logs_argv(container: str) -> list[str]:
    """Follow the container's output from its start (ends when the container does)."""
    return [binary(), "logs", "--follow", container]
