"""A fake lab for the scenario engine: links from a real `Topology`, "daemons" that list
exactly the medium's truth (but for `blind` pairs), and the `fake` fixture giving a `Backend`
that makes such labs."""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any, cast

import msgspec
import pytest

from netlab.errors import LabStateError
from netlab.ranges import Pos, Topology
from netlab.scenario import Backend, LabSpec
from sdfr.errors import ApiError
from sdfr.records.model import ServiceOutput
from sdfr.records.schema import Neighbor, PeerJson


class FakeRobot:
    def __init__(self, name: str, mac: str) -> None:
        self.name = name
        self.mac = mac
        self.ns = f"fake-{name}"
        self.iface = "eth0"
        self.log = Path("/nonexistent") / f"{name}.log"


class FakeMedium:
    ns = "fake-air"


class FakeLab:
    """Links from a real Topology; its "daemons" list exactly the truth, but for `blind`
    pairs (robot, peer) they never list."""

    def __init__(self, spec: LabSpec) -> None:
        self.name = spec.name
        self.spec = spec
        self.medium = FakeMedium()
        self.topology = Topology(spec.range_model)
        self.robots: dict[str, FakeRobot] = {}
        self.running: set[str] = set()
        self.crashed: dict[str, str] = {}
        self.services: dict[str, dict[str, str]] = {}
        self.heard: dict[str, set[str]] = {}
        self.blind: set[tuple[str, str]] = set()
        self.calls: list[tuple[Any, ...]] = []
        self.bias: dict[tuple[str, str], float] = {}
        #: A robot's daemon answers a publish only after this many seconds (a stalled machine):
        #: a client that waits less gets "timed out".
        self.stall: dict[str, float] = {}
        self.lock = threading.Lock()
        self.state = "new"

    def up(self) -> FakeLab:
        self.state = "up"
        return self

    def down(self) -> None:
        self.state = "down"
        self.running.clear()

    def add_robot(
        self,
        name: str,
        *,
        pos: Pos = (0.0, 0.0),
        mac: str | None = None,
        runtime: str | None = None,
    ) -> None:
        self.robots[name] = FakeRobot(name, mac or f"02:00:00:00:00:{len(self.robots) + 1:02x}")
        self.topology.add(name, pos)
        self.services[name] = {}
        self.heard[name] = set()

    def robot(self, ref: str) -> FakeRobot:
        return self.robots[ref]

    def batch(self) -> contextlib.AbstractContextManager[None]:
        return contextlib.nullcontext()

    def start_all(self, refs: Any = None, *, timeout: float = 60, **options: Any) -> None:
        for r in refs if refs is not None else list(self.robots):
            self.start(r, **options)

    def start(self, ref: str, *, timeout: float = 20, **options: Any) -> None:
        if ref in self.running:
            raise LabStateError(f"sdfrd already runs on robot {ref}; stop it first")
        self.calls.append(("start", ref, options.get("beacon_interval")))
        self.running.add(ref)

    def stop(self, ref: str, timeout: float = 10) -> int:
        self._running(ref)
        self.calls.append(("stop", ref))
        self.running.discard(ref)
        return 0

    def kill(self, ref: str) -> None:
        self._running(ref)
        self.calls.append(("kill", ref))
        self.running.discard(ref)

    def crash(self, ref: str, how: str = "signal 9 (SIGKILL)") -> None:
        """sdfrd on `ref` ends without the lab asking (a crash, a kill from elsewhere)."""
        self._running(ref)
        self.running.discard(ref)
        self.crashed[ref] = how

    def daemons_ended(self) -> dict[str, str]:
        return dict(self.crashed)

    def restart(self, ref: str, *, timeout: float = 20, **options: Any) -> None:
        self.calls.append(("restart", ref))
        self.running.add(ref)

    def _running(self, ref: str) -> None:
        if ref not in self.running:
            raise LabStateError(f"sdfrd is not running on robot {ref}")

    def partition(self, groups: Any) -> None:
        groups = [list(g) for g in groups]
        self.calls.append(("partition", groups))
        self.topology.partition(groups)

    def merge(self) -> None:
        self.calls.append(("merge",))
        self.topology.merge()

    def move(self, ref: str, pos: Pos) -> None:
        self.calls.append(("move", ref))
        self.topology.move(ref, pos)

    def set_pair_quality(self, a: str, b: str, *, loss: float | None, both: bool = True) -> None:
        self.calls.append(("quality", a, b, loss, both))
        self.topology.set_pair_quality(a, b, loss, both)

    def shape(self, ref: str, **params: Any) -> None:
        self.calls.append(("shape", ref, params))

    def links(self) -> dict[tuple[str, str], float]:
        return self.topology.links()

    def daemon_pid(self, ref: str) -> int | None:
        return os.getpid() if ref in self.running else None  # the test itself, for /proc

    def positions(self) -> dict[str, Pos]:
        return dict(self.topology.positions)

    def listing(self, robot: str) -> set[str]:
        if robot not in self.running:
            raise ApiError(0, f"cannot reach sdfrd of {robot}")
        links = self.links()
        peers = {a for (a, b) in links if b == robot and a in self.running}
        peers -= {p for (r, p) in self.blind if r == robot}
        self.heard[robot] |= peers
        return peers


class FakeClient:
    def __init__(self, lab: FakeLab, robot: str, timeout: float = 2.0) -> None:
        self.lab = lab
        self.robot = robot
        self.timeout = timeout

    def _entry(self, peer: str, reachable: bool) -> dict[str, Any]:
        """`peer` as sdfrd's API shows it: a history map's robot (`PeerJson`); a neighbour
        list's entries are the same less the fields only the history has."""
        services = [
            ServiceOutput(id=sid, name=name, type="sensor.fake", url=None, attributes={})
            for sid, name in self.lab.services[peer].items()
        ]
        address = f"10.1.0.{list(self.lab.robots).index(peer) + 1}"
        # The indicator: the medium's round-trip delivery (+ a test's bias); half of it once
        # the peer is gone (its last pings were lost).
        links = self.lab.links()
        there, back = links.get((self.robot, peer)), links.get((peer, self.robot))
        ind = None
        if there is not None and back is not None:
            ind = (1 - there / 100) * (1 - back / 100) + self.lab.bias.get((self.robot, peer), 0)
            ind = ind if reachable else ind / 2
        entry = PeerJson(
            robot_id=peer,
            address=address,
            location=f"http://{address}:8701/description.json",
            reachable=reachable,
            indicator=ind,
            rtt_ms=None if ind is None else 1.0,
            boot_id=1,
            version=len(services),
            first_seen=0.0,
            last_seen=0.0,
            services=services,
        )
        return cast(dict[str, Any], msgspec.to_builtins(entry))

    def neighbors(self, include_unreachable: bool = False) -> list[dict[str, Any]]:
        return [self._neighbor(p) for p in sorted(self.lab.listing(self.robot))]

    def _neighbor(self, peer: str) -> dict[str, Any]:
        fields = {f.name for f in msgspec.structs.fields(Neighbor)}
        return {k: v for k, v in self._entry(peer, True).items() if k in fields}

    def history(self) -> list[dict[str, Any]]:
        now = self.lab.listing(self.robot)
        return [self._entry(p, p in now) for p in sorted(self.lab.heard[self.robot])]

    def publish(
        self,
        name: str,
        type: str,
        url: str | None = None,
        attributes: Mapping[str, Any] | None = None,
    ) -> str:
        if self.robot not in self.lab.running:
            raise ApiError(0, "cannot reach sdfrd")
        if self.lab.stall.get(self.robot, 0.0) > self.timeout:
            raise ApiError(0, f"cannot reach sdfrd of {self.robot}: timed out")
        sid = f"{self.robot}-{name}"
        self.lab.services[self.robot][sid] = name
        return sid

    def unpublish(self, service_id: str) -> None:
        del self.lab.services[self.robot][service_id]

    def self_info(self) -> dict[str, Any]:
        return {"address": f"10.1.0.{list(self.lab.robots).index(self.robot) + 1}"}

    def close(self) -> None:
        pass


@pytest.fixture
def fake() -> Iterator[tuple[Backend, list[FakeLab]]]:
    labs: list[FakeLab] = []

    def make(spec: LabSpec) -> FakeLab:
        lab = FakeLab(spec)
        labs.append(lab)
        return lab

    def connect(lab: Any, robot: str, timeout: float) -> FakeClient:
        return FakeClient(lab, robot, timeout)

    flags = frozenset({"beacon_interval", "miss_limit", "ping_window"})
    yield Backend(make, connect, lambda spec: flags, can_capture=False), labs
    assert all(lab.state == "down" for lab in labs)


BEACON = 0.05


def quiet(lines: list[str]) -> Any:
    return lines.append
