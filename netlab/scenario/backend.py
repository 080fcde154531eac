"""What the engine needs of a lab, a robot's daemon and time: the real ones (`Backend()`),
or fakes a test gives (a fake lab, fake clients, a `netlab.clock.VirtualClock`)."""

from __future__ import annotations

import re
import subprocess
import sys
from collections.abc import Callable, Iterable, Mapping
from contextlib import AbstractContextManager
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any, Protocol

from netlab.clock import REAL, Clock
from netlab.docker import DEFAULT_IMAGE
from netlab.errors import NetlabError
from netlab.observe import ClientLike
from netlab.ranges import Pos, RangeModel


class RobotLike(Protocol):
    @property
    def ns(self) -> str: ...

    @property
    def mac(self) -> str: ...

    @property
    def iface(self) -> str: ...

    @property
    def log(self) -> Path: ...


class MediumLike(Protocol):
    @property
    def ns(self) -> str: ...


class LabLike(Protocol):
    @property
    def name(self) -> str: ...

    @property
    def medium(self) -> MediumLike: ...

    def up(self) -> object: ...

    def down(self) -> object: ...

    def add_robot(
        self, name: str, *, pos: Pos = ..., mac: str | None = ..., runtime: str | None = ...
    ) -> object: ...

    def robot(self, ref: str) -> RobotLike: ...

    def batch(self) -> AbstractContextManager[None]: ...

    def start_all(
        self, refs: Iterable[str] | None = ..., *, timeout: float = ..., **options: Any
    ) -> None: ...

    def start(self, ref: str, *, timeout: float = ..., **options: Any) -> None: ...

    def stop(self, ref: str, timeout: float = ...) -> int: ...

    def kill(self, ref: str) -> None: ...

    def daemons_ended(self) -> dict[str, str]: ...

    def restart(self, ref: str, *, timeout: float = ..., **options: Any) -> None: ...

    def partition(self, groups: Iterable[Iterable[str]]) -> None: ...

    def merge(self) -> None: ...

    def move(self, ref: str, pos: Pos) -> None: ...

    def set_pair_quality(self, a: str, b: str, *, loss: float | None, both: bool = ...) -> None: ...

    def shape(self, ref: str, **params: Any) -> object: ...

    def links(self) -> Mapping[tuple[str, str], float]: ...

    def positions(self) -> dict[str, Pos]: ...


@dataclass(frozen=True, slots=True)
class LabSpec:
    """The lab a scenario asks for."""

    name: str
    seed: int
    fleet: int
    range_model: RangeModel
    addressing: str = "manual"
    runtime: str = "namespace"
    image: str = DEFAULT_IMAGE
    medium: str = "wired"
    air_medium: str = "netlab"


def _real_lab(spec: LabSpec) -> LabLike:
    import inspect

    from netlab.lab import Lab

    extra: dict[str, Any] = {}
    if spec.addressing != "manual":
        if "addressing" not in inspect.signature(Lab).parameters:
            raise NetlabError(f"this netlab's Lab cannot do addressing = {spec.addressing}")
        extra["addressing"] = spec.addressing
    if spec.runtime != "namespace":
        extra.update(runtime=spec.runtime, image=spec.image)
    if spec.medium != "wired":
        extra["air"] = spec.medium
        extra["air_medium"] = spec.air_medium
    return Lab(spec.name, seed=spec.seed, fleet=spec.fleet, range_model=spec.range_model, **extra)


#: How long the observer waits for a robot's answer before its sample says "error": a sample
#: is a measurement, and a late one is worth less than the next.
SAMPLE_TIMEOUT = 2.0
#: How long a step (a publish, a check's question) waits for a robot's answer: an action is not
#: a measurement, and a machine that stalls for seconds (the VM tiers' emulated CPU, where a
#: 6 s stall of the whole VM failed a publish after its three 2 s tries) must not fail the run.
STEP_TIMEOUT = 15.0


def _real_client(lab: LabLike, robot: str, timeout: float) -> ClientLike:
    from netlab.lab import Lab
    from sdfr.client import Client

    assert isinstance(lab, Lab)
    return Client(unix_socket=lab.robot(robot).api_socket, timeout=timeout)


def sdfrd_flags(spec: LabSpec) -> frozenset[str]:
    """The options `sdfrd --help` lists, as the lab's robots run it (the host's sdfrd, or the
    robot image's), without dashes."""
    if spec.runtime == "docker":
        from netlab import docker

        docker.require_image(spec.image)
        run = (docker.binary(), "run", "--rm", "--network", "none")
        return _flags((*run, "--entrypoint", "/opt/sdfr/bin/sdfrd", spec.image, "--help"))
    return _flags((sys.executable, "-m", "sdfr.daemon", "--help"))


@cache
def _flags(argv: tuple[str, ...]) -> frozenset[str]:
    try:
        res = subprocess.run(
            argv,
            capture_output=True,
            text=True,
            timeout=60,
            stdin=subprocess.DEVNULL,
        )
    except (OSError, subprocess.SubprocessError) as exc:
        raise NetlabError(f"cannot run sdfrd --help: {exc}") from None
    return frozenset(m.replace("-", "_") for m in re.findall(r"--([a-z][a-z0-9-]*)", res.stdout))


@dataclass(frozen=True)
class Backend:
    """How the engine makes a lab, talks to a robot's daemon, and learns sdfrd's options."""

    make_lab: Callable[[LabSpec], LabLike] = _real_lab
    #: A client of a robot's daemon that waits `timeout` seconds for an answer.
    connect: Callable[[LabLike, str, float], ClientLike] = _real_client
    flags: Callable[[LabSpec], frozenset[str]] = sdfrd_flags
    #: Whether tcpdump can run in the lab's namespaces.
    can_capture: bool = True
    #: Time: the engine's deadlines, sleeps and samples.
    clock: Clock = REAL
