"""A lab: robots on one medium, running the real sdfrd, each in its own network namespace.

Robots are namespaces (``runtime="namespace"``, the default) or containers of the robot
image (``runtime="docker"``); see `netlab.robots` for the kinds.  The medium, shaping,
captures and scenarios work on any kind.

    with Lab("demo", seed=1) as lab:
        for i in range(3):
            lab.add_robot(f"r{i + 1}", pos=(i * 5.0, 0.0))
        lab.start_all(beacon_interval=0.5)
        lab.partition([["r1"], ["r2", "r3"]])
        ...

Everything a lab creates is recorded in its manifest before it is created,
and `down()` (also `netlab down NAME` from another process, after this one
died) removes exactly that: see `netlab.cleanup`.

`Lab` is three parts of one job each: this module's life cycle and robots,
`netlab.labmedium`'s medium (partitions, moves, shaping, the links' truth) and
`netlab.daemons`' processes (sdfrd, its options checked before it starts, and commands).

Robot ``i`` (from 0, in order of `add_robot`) gets the address
``10.<fleet>.<i // 250>.<i % 250 + 1>/16`` and, unless given, a MAC
derived from the lab's seed and ``i``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import select
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterable, Mapping
from ipaddress import IPv4Interface
from pathlib import Path
from types import TracebackType
from typing import Any

from netlab import airmedium, cleanup, docker, hostlimits, hwsim, kernel, manifest, naming, shaping
from netlab.cleanup import SweepResult
from netlab.daemons import START_TIMEOUT, STOP_TIMEOUT, SUN_PATH_MAX, LabProcesses
from netlab.doctor import capabilities
from netlab.errors import (
    LabExistsError,
    LabNotFoundError,
    LabStateError,
    NetlabError,
    UnknownRobotError,
    kernel_errors,
)
from netlab.labmedium import LabMedium
from netlab.manifest import Manifest, ProcRecord, RobotRecord
from netlab.medium import Medium
from netlab.ranges import Pos, RangeModel, Topology
from netlab.robots import AIR_MEDIA, AIRS, RUNTIMES, Daemon, Robot, RobotKind, RobotRef, kind_for
from netlab.shaping import LinkShape
from netlab.vxlan import Span
from sdfr.client import Client

#: Seconds the radio medium may take to start and register (a Python start, under emulation).
AIR_START_TIMEOUT = 60.0

__all__ = ["START_TIMEOUT", "STOP_TIMEOUT", "SUN_PATH_MAX", "Lab", "Robot", "RobotRef"]


def _write_secret(path: Path, secret: str) -> None:
    with kernel_errors(f"writing the lab's WiFi secret {path}"):
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as out:
            out.write(secret + "\n")


class Lab(LabProcesses, LabMedium):
    """A fleet of robots on one medium; a context manager (or `up()`/`down()`).

    `runtime` is the kind of robot `add_robot` makes unless told otherwise: "namespace" or
    "docker" (containers of `image`, which must be here: ``make image`` builds it).
    `air` is what they meet on (a scenario's `medium`): "wired", a bridge whose rules make
    ranges, partitions and loss, or "radio", one mac80211_hwsim radio per robot on which its
    sdfrd joins the fleet's WiFi itself (the lab's random secret, `wifi_secret_file`, unless
    told otherwise); the lab's medium (`netlab.airmedium`, a process started at `up`)
    delivers their frames by the same links as the wired rules (moves, partitions, pair
    loss); shaping a radio link says it needs the wired medium.
    """

    def __init__(
        self,
        name: str,
        *,
        seed: int = 0,
        workdir: Path | None = None,
        fleet: int = 1,
        range_model: RangeModel | None = None,
        addressing: str = "manual",
        runtime: str = "namespace",
        image: str = docker.DEFAULT_IMAGE,
        air: str = "wired",
        air_medium: str = "netlab",
        span: Span | None = None,
    ) -> None:
        self.name = naming.check_lab_name(name)
        if addressing not in ("manual", "auto"):
            raise NetlabError(f"addressing: must be manual or auto, got {addressing!r}")
        if runtime not in RUNTIMES:
            raise NetlabError(f"runtime: one of {', '.join(RUNTIMES)}, got {runtime!r}")
        if air not in AIRS:
            raise NetlabError(f"medium: one of {', '.join(AIRS)}, got {air!r}")
        if air == "radio" and runtime != "namespace":
            raise NetlabError("medium radio: its robots are namespaces (runtime namespace)")
        if air_medium not in AIR_MEDIA:
            raise NetlabError(f"air_medium: one of {', '.join(AIR_MEDIA)}, got {air_medium!r}")
        #: wired: every robot's eth0 on one bridge, the medium's rules between them; radio:
        #: each robot a mac80211_hwsim radio, and sdfrd joins the fleet's WiFi on it.
        self.air = air
        #: A radio lab's medium: "netlab" (`netlab.airmedium`: the range model decides who
        #: hears a frame) or "hwsim" (the kernel's own: every radio hears every other at once,
        #: no moves or partitions).
        self.air_medium = air_medium
        if span is not None and air != "wired":
            raise NetlabError("a lab across hosts (span) runs on the wired medium")
        #: This host's end of a lab across hosts (`netlab.vxlan`): its medium is joined to the
        #: other hosts' over VXLAN, their robots are `add_remote`'s.
        self.span = span
        self._remote: dict[str, str] = {}
        self._hwsim: hwsim.Hwsim | None = None
        self._radio_addrs: dict[str, str] = {}
        self.runtime = runtime
        self.image = image
        self._kinds: dict[str, RobotKind] = {}
        #: manual: the lab gives each robot a static address; auto: robots start without one
        #: and sdfrd derives, probes and defends its own (`sdfrd --addressing auto`).
        self.addressing = addressing
        naming.address_for(fleet, 0)  # validates the fleet number
        self.seed = seed
        self.fleet = fleet
        self._workdir_arg = workdir
        self.workdir = Path()
        self.topology = Topology(range_model)
        self.medium = Medium(naming.air_ns(name))
        self._robots: dict[str, Robot] = {}
        self._macs: set[str] = set()
        self._record: Manifest | None = None
        self._state = "new"  # new -> up -> down (or detached)
        self._batch = 0
        self._shapes: dict[str, LinkShape] = {}
        self._nft_loss: dict[str, float] = {}
        self._daemons: dict[str, Daemon] = {}
        self._daemon_opts: dict[str, dict[str, Any]] = {}
        self._ended_by_lab: set[str] = set()
        self._procs: list[subprocess.Popen[Any]] = []
        self._clients: dict[str, Client] = {}
        self.setup_seconds: dict[str, float] = {}
        self._other_labs_entries = 0

    # -- life cycle ----------------------------------------------------------------------

    def __enter__(self) -> Lab:
        return self.up()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        # A block that failed keeps the lab's folder (its robots' daemon logs and state), as
        # `netlab down` does, and its error says where; one that ended well leaves nothing.
        failed = isinstance(exc, Exception)
        kept = self.down(keep_workdir=failed).kept
        if isinstance(exc, Exception) and kept:
            note = f"lab {self.name}: its folder (daemon logs, state) is kept in {kept}"
            if hasattr(exc, "add_note"):  # (Python 3.11)
                exc.add_note(note)
            else:
                print(f"netlab: {note}", file=sys.stderr)

    def __repr__(self) -> str:
        return f"<Lab {self.name} {self._state}, {len(self._robots)} robots>"

    @property
    def is_up(self) -> bool:
        return self._state == "up"

    def up(self) -> Lab:
        """Claim the name, create the medium; on any failure remove what was made and re-raise."""
        if self._state != "new":
            raise LabStateError(f"lab {self.name} is {self._state}; make a new Lab to start again")
        if os.geteuid() != 0:
            raise NetlabError("netlab needs root (namespaces, veths, nftables): run it with sudo")
        me = os.getpid()
        record = Manifest(self.name, self.seed, self.fleet, runner_pid=me)
        record.runner_start = cleanup.start_time(me) or 0
        record.runtime, record.addressing, record.air = self.runtime, self.addressing, self.air
        record.image = self.image if self.runtime == "docker" else ""
        manifest.claim(record)
        self._record = record
        self._state = "up"
        try:
            left = []
            if namespaces := kernel.list_ns(naming.prefix(self.name)):
                left.append(f"namespaces {', '.join(namespaces)}")
            if self.runtime == "docker":
                docker.require_image(self.image)
                if containers := docker.labelled(self.name):
                    left.append(f"containers {', '.join(containers)}")
            if left:
                raise LabExistsError(
                    f"{' and '.join(left)} of a lab {self.name!r} exist without a "
                    f"runner; `netlab down {self.name}` removes them"
                )
            if self._workdir_arg is None:
                self.workdir = Path(tempfile.mkdtemp(prefix=f"netlab-{self.name}-"))
                record.workdir_owned = True
            else:
                self.workdir = Path(self._workdir_arg).absolute()
                with kernel_errors(f"creating the workdir {self.workdir}"):
                    self.workdir.mkdir(parents=True, exist_ok=True)
            record.workdir = str(self.workdir)
            self._other_labs_entries = sum(
                hostlimits.mesh_entries(len(other.robots)) for other in manifest.others(self.name)
            )
            record.namespaces.append(self.medium.ns)
            manifest.save(record)
            self.medium.create()
            if self.span is not None:
                self.medium.span(self.span)
            if self.air == "radio":
                self._hwsim = hwsim.Hwsim()
                _write_secret(self.wifi_secret_file, os.urandom(24).hex())
                if self.air_medium == "netlab":
                    self._start_air()
        except LabExistsError:
            # The leftovers are not ours to touch: release the name, leave them for `down`.
            manifest.remove(self.name)
            self._state = "down"
            raise
        except BaseException:
            self.down()
            raise
        return self

    def down(self, *, keep_workdir: bool = False) -> SweepResult:
        """Stop every process and remove every object of the lab (its folder too, unless
        `keep_workdir`); idempotent."""
        if self._state != "up":
            return SweepResult()
        self._state = "down"
        self._close_clients()
        self.medium.close()
        if self._hwsim is not None:
            self._hwsim.close()
            self._hwsim = None
        try:
            result = cleanup.sweep(self.name, self._record, keep_workdir=keep_workdir)
        finally:
            for proc in [*self._daemons.values(), *self._procs]:
                with contextlib.suppress(subprocess.TimeoutExpired):
                    proc.wait(timeout=1.0)  # reap: they were killed by the sweep
        return result

    def detach(self) -> None:
        """Leave the lab running for `netlab down` to remove later; close our handles.

        The medium's state is written into the manifest, so that another process can take
        the lab over (`Lab.attach`) and change it: `netlab partition`, `merge`, `shape`.
        """
        self._check_up()
        assert self._record is not None
        topology = self.topology.to_json()
        if topology is not None:
            shapes = {r: dataclasses.asdict(s) for r, s in self._shapes.items()}
            self._record.medium = {**topology, "shapes": shapes}
        self._record.detached = True
        self._save()
        self._close_clients()
        self.medium.close()
        if self._hwsim is not None:
            self._hwsim.close()
            self._hwsim = None
        self._state = "detached"

    @classmethod
    def attach(cls, name: str) -> Lab:
        """Take over lab `name`, left running by `detach()` (`netlab up`): its medium can be
        changed, commands run in its robots, its daemons asked; `detach()` again when done.
        Hold `manifest.locked(name)` meanwhile when other processes may do the same."""
        record = manifest.load(naming.check_lab_name(name))
        if record is None:
            raise LabNotFoundError(f"no lab {name} is up (`netlab status` lists labs)")
        runner = cleanup.running(record.runner_pid) and (
            cleanup.start_time(record.runner_pid) == record.runner_start
        )
        if not record.detached:
            raise LabStateError(
                f"lab {name} is run by pid {record.runner_pid}, which keeps its medium's state: "
                "change it there"
                if runner
                else f"lab {name} was not left up by `netlab up` and its runner "
                f"(pid {record.runner_pid}) is gone: `netlab down {name}` removes it"
            )
        if not record.medium:
            raise LabStateError(f"lab {name}'s medium cannot be rebuilt (a custom range model)")
        lab = cls(
            name,
            seed=record.seed,
            fleet=record.fleet,
            workdir=Path(record.workdir),
            range_model=Topology.from_json(record.medium).model,
            addressing=record.addressing,
            runtime=record.runtime,
            image=record.image or docker.DEFAULT_IMAGE,
            air=record.air,
        )
        lab._adopt(record)
        return lab

    def _adopt(self, record: Manifest) -> None:
        self._record = record
        self.workdir = Path(record.workdir)
        self.topology = Topology.from_json(record.medium)
        for name, r in record.robots.items():
            robot = Robot(
                name, r.index, r.ns, r.port, r.mac, IPv4Interface(r.address),
                self.workdir / name, r.runtime, r.iface,
            )  # fmt: skip
            self._robots[name] = robot
            self._macs.add(robot.mac)
        for name, params in record.medium.get("shapes", {}).items():
            shape = LinkShape.of(**params)
            self._shapes[name] = shape
            loss = shaping.plan(shape, capabilities()).nft_loss
            if loss:
                self._nft_loss[name] = loss
        self._other_labs_entries = sum(
            hostlimits.mesh_entries(len(other.robots)) for other in manifest.others(self.name)
        )
        self.medium.open()
        if self.air == "radio":
            self._hwsim = hwsim.Hwsim()
            if not self.air_links_file.exists():  # (no medium of netlab's: hwsim's own)
                self.air_medium = "hwsim"
            else:
                table = airmedium.read_links(self.air_links_file)
                self._radio_addrs = {r: naming.mac_text(a) for a, r in table.radios.items()}
        self._state = "up"

    def _start_air(self) -> None:
        """Start the radio medium (`netlab.airmedium`), recorded as a lab process, and wait
        until it is hwsim's medium; NetlabError with its reason if it cannot be."""
        assert self._record is not None
        self.air_links_file.parent.mkdir(exist_ok=True)
        airmedium.write_links(self.air_links_file, {}, {})
        argv = [
            sys.executable, "-m", "netlab.airmedium", "--links", str(self.air_links_file),
            "--stats", str(self.air_stats_file), "--seed", str(self.seed),
        ]  # fmt: skip
        log_path = self.air_links_file.parent / "medium.log"
        with kernel_errors("starting the radio medium"), open(log_path, "ab") as log:
            proc = subprocess.Popen(
                argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=log,
                start_new_session=True, cwd=Path(__file__).resolve().parent.parent,
            )  # fmt: skip
        self._procs.append(proc)
        self._record.processes.append(
            ProcRecord(proc.pid, cleanup.start_time(proc.pid) or 0, "", "medium", argv)
        )
        self._save()
        assert proc.stdout is not None
        line = b""  # "registered", or nothing when it ended
        if select.select([proc.stdout], [], [], AIR_START_TIMEOUT)[0]:
            line = proc.stdout.readline()
        proc.stdout.close()
        if line.strip() != b"registered":
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=5.0)
            said = log_path.read_text(errors="replace").strip().splitlines()
            raise NetlabError(
                f"lab {self.name}: the radio medium did not start "
                f"(exit {proc.poll()}): {said[-1] if said else 'it said nothing'}"
                if proc.poll() is not None
                else f"lab {self.name}: the radio medium did not register within "
                f"{AIR_START_TIMEOUT:.0f} s"
            )

    def _check_up(self) -> None:
        if self._state != "up":
            raise LabStateError(f"lab {self.name} is {self._state}, not up")

    def _save(self) -> None:
        assert self._record is not None
        manifest.save(self._record)

    # -- robots --------------------------------------------------------------------------

    @property
    def robots(self) -> dict[str, Robot]:
        """The robots, by name, in the order they were added."""
        return dict(self._robots)

    def robot(self, ref: RobotRef) -> Robot:
        name = ref.name if isinstance(ref, Robot) else ref
        try:
            return self._robots[name]
        except KeyError:
            raise UnknownRobotError(
                f"lab {self.name} has no robot {name!r} (robots: {', '.join(self._robots)})"
            ) from None

    def _auto_mac(self, index: int) -> str:
        salt = 0
        while True:  # a hash collision inside one lab is unlikely, never silent
            mac = naming.mac_for(self.seed + salt * 1_000_003, index)
            if mac not in self._macs:
                return mac
            salt += 1

    def kind(self, runtime: str) -> RobotKind:
        """The robot kind of `runtime` ("namespace" or "docker"), one per lab."""
        if runtime not in self._kinds:
            if runtime == "docker" and self.runtime != "docker":
                docker.require_image(self.image)
            self._kinds[runtime] = kind_for(runtime, self.image)
        return self._kinds[runtime]

    def add_robot(
        self,
        name: str,
        *,
        pos: Pos = (0.0, 0.0),
        mac: str | None = None,
        runtime: str | None = None,
        index: int | None = None,
    ) -> Robot:
        """A robot whose namespace has eth0 on the medium, lo up and a multicast route.

        `mac` defaults to one derived from the lab's seed and the robot's index; a
        given one may repeat another robot's (to script an address collision).
        `runtime` defaults to the lab's: a lab may mix kinds.  `index` (default: the
        next) numbers the robot's address and MAC: a lab across hosts numbers its robots
        across all hosts.
        """
        self._check_up()
        assert self._record is not None
        naming.check_robot_name(name)
        if name in self._robots:
            raise NetlabError(f"lab {self.name} already has a robot {name!r}")
        t0 = time.perf_counter()
        # The kernel's ARP table is shared by all namespaces: make room for the mesh.
        hostlimits.ensure(self._other_labs_entries + hostlimits.mesh_entries(len(self._robots) + 1))
        if index is None:
            index = len(self._robots)
        elif index < 0 or index in (r.index for r in self._robots.values()):
            raise NetlabError(
                f"robot {name}: index {index} is negative or taken in lab {self.name}"
            )
        mac = naming.check_mac(mac) if mac is not None else self._auto_mac(index)
        runtime = runtime or self.runtime
        kind = self.kind(runtime)
        robot = Robot(
            name=name,
            index=index,
            ns=naming.robot_ns(self.name, name),
            port=naming.port(name),
            mac=mac,
            address=naming.address_for(self.fleet, index),
            workdir=self.workdir / name,
            runtime=runtime,
        )
        self.topology.add(name, pos)  # validates pos before anything is created
        self._robots[name] = robot
        self._macs.add(mac)
        self._record.namespaces.append(robot.ns)
        self._record.containers += robot.containers
        self._record.robots[name] = RobotRecord(
            robot.index, robot.ns, robot.port, robot.mac, str(robot.address), runtime,
            radio=robot.ns if self.air == "radio" else "",
        )  # fmt: skip
        self._save()
        try:
            robot = self._plumb(robot, kind)
        except BaseException:
            # Leave the lab as it was: no half-made robot. Its veth goes with its namespace.
            with contextlib.suppress(NetlabError):
                kind.discard(self.name, robot)
            del self._robots[name]
            self.topology.positions.pop(name, None)
            if mac not in (r.mac for r in self._robots.values()):
                self._macs.discard(mac)
            self._record.namespaces.remove(robot.ns)
            for container in robot.containers:
                self._record.containers.remove(container)
            del self._record.robots[name]
            self._save()
            raise
        self._changed()
        self.setup_seconds[name] = time.perf_counter() - t0
        return robot

    def _plumb(self, robot: Robot, kind: RobotKind) -> Robot:
        """Make the robot's namespace and its link; the robot, with its link's name."""
        kind.create(self.name, robot)
        kernel.ipv4_only(robot.ns)  # before its link exists, so that it inherits the default
        if self._hwsim is not None:
            # The radio is named as the namespace: a sweep finds it by the lab's prefix.
            radio, iface = hwsim.adopt(self._hwsim, robot.ns, robot.ns)
            self._radio_addrs[robot.name] = radio.address
            robot = dataclasses.replace(robot, iface=iface)
            self._robots[robot.name] = robot
            assert self._record is not None
            self._record.robots[robot.name].iface = iface
            self._save()
        else:
            self.medium.attach(robot.ns, robot.port, robot.mac)
        address = robot.address if self.addressing == "manual" else None
        # Across hosts, room for VXLAN's header on the way to the other hosts.
        mtu = self.span.mtu if self.span is not None else None
        doing = f"configuring {robot.iface} of robot {robot.name}"
        kernel.bring_up(robot.ns, robot.iface, address, doing, mtu=mtu)
        return robot

    def add_remote(self, name: str, *, mac: str, pos: Pos = (0.0, 0.0)) -> None:
        """A robot of another host of this lab across hosts (see `span`): on the medium's
        map at `pos`, its frames (arriving over VXLAN, known by `mac`) judged by the range
        model like a local robot's; moved, partitioned and given pair loss by name."""
        self._check_up()
        if self.span is None:
            raise NetlabError(f"lab {self.name} spans no hosts: a remote robot needs a span")
        naming.check_robot_name(name)
        if name in self._robots or name in self._remote:
            raise NetlabError(f"lab {self.name} already has a robot {name!r}")
        self.topology.add(name, pos)
        self._remote[name] = naming.check_mac(mac)
        self._changed()

    @property
    def wifi_secret_file(self) -> Path:
        """A radio lab's WiFi secret (random, made at `up`): every robot's sdfrd joins the
        fleet's network with it unless given another `wifi_secret_file`."""
        return self.workdir / "wifi-secret"

    def add_robots(
        self, names: Iterable[str], positions: Mapping[str, Pos] | None = None
    ) -> list[Robot]:
        """Several robots, with the medium rules loaded once at the end."""
        with self.batch():
            return [self.add_robot(n, pos=(positions or {}).get(n, (0.0, 0.0))) for n in names]

    def live_addresses(self, ref: RobotRef) -> list[str]:
        """The IPv4 addresses eth0 has right now (with `addressing="auto"`, sdfrd's choice)."""
        robot = self.robot(ref)
        doing = f"reading the addresses of robot {robot.name}"
        return kernel.addresses(robot.ns, robot.iface, doing)
