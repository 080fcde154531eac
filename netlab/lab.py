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

Robot ``i`` (from 0, in order of `add_robot`) gets the address
``10.<fleet>.<i // 250>.<i % 250 + 1>/16`` and, unless given, a MAC
derived from the lab's seed and ``i``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import signal
import subprocess
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from ipaddress import IPv4Interface
from pathlib import Path
from types import TracebackType
from typing import Any, cast

from netlab import cleanup, docker, hostlimits, kernel, manifest, naming, shaping
from netlab.cleanup import SweepResult
from netlab.doctor import capabilities
from netlab.errors import (
    DaemonError,
    LabExistsError,
    LabNotFoundError,
    LabStateError,
    NetlabError,
    UnknownRobotError,
    kernel_errors,
)
from netlab.manifest import Manifest, ProcRecord, RobotRecord
from netlab.medium import Medium
from netlab.mobility import MobilityModel, walk
from netlab.ranges import Links, Pos, RangeModel, Topology, with_link_loss
from netlab.robots import RUNTIMES, Daemon, NamespaceKind, Robot, RobotKind, kind_for
from netlab.shaping import LinkShape
from sdfr.client import Client
from sdfr.errors import ApiError

START_TIMEOUT = 20.0
STOP_TIMEOUT = 10.0
SUN_PATH_MAX = 107  # a unix socket path longer than this cannot be bound


RobotRef = str | Robot


__all__ = ["Lab", "Robot", "RobotRef"]


class Lab:
    """A fleet of robots on one medium; a context manager (or `up()`/`down()`).

    `runtime` is the kind of robot `add_robot` makes unless told otherwise: "namespace" or
    "docker" (containers of `image`, which must be here: ``make image`` builds it).
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
    ) -> None:
        self.name = naming.check_lab_name(name)
        if addressing not in ("manual", "auto"):
            raise NetlabError(f"addressing: must be manual or auto, got {addressing!r}")
        if runtime not in RUNTIMES:
            raise NetlabError(f"runtime: one of {', '.join(RUNTIMES)}, got {runtime!r}")
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
        self.down()

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
        record.runtime, record.addressing = self.runtime, self.addressing
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
        except LabExistsError:
            # The leftovers are not ours to touch: release the name, leave them for `down`.
            manifest.remove(self.name)
            self._state = "down"
            raise
        except BaseException:
            self.down()
            raise
        return self

    def down(self) -> SweepResult:
        """Stop every process and remove every object of the lab; idempotent."""
        if self._state != "up":
            return SweepResult()
        self._state = "down"
        for client in self._clients.values():
            client.close()
        self._clients.clear()
        self.medium.close()
        try:
            result = cleanup.sweep(self.name, self._record)
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
        for client in self._clients.values():
            client.close()
        self._clients.clear()
        self.medium.close()
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
                self.workdir / name, r.runtime,
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
        self._state = "up"

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
    ) -> Robot:
        """A robot whose namespace has eth0 on the medium, lo up and a multicast route.

        `mac` defaults to one derived from the lab's seed and the robot's index; a
        given one may repeat another robot's (to script an address collision).
        `runtime` defaults to the lab's: a lab may mix kinds.
        """
        self._check_up()
        assert self._record is not None
        naming.check_robot_name(name)
        if name in self._robots:
            raise NetlabError(f"lab {self.name} already has a robot {name!r}")
        t0 = time.perf_counter()
        # The kernel's ARP table is shared by all namespaces: make room for the mesh.
        hostlimits.ensure(self._other_labs_entries + hostlimits.mesh_entries(len(self._robots) + 1))
        index = len(self._robots)
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
            robot.index, robot.ns, robot.port, robot.mac, str(robot.address), runtime
        )
        self._save()
        try:
            self._plumb(robot, kind)
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

    def _plumb(self, robot: Robot, kind: RobotKind) -> None:
        kind.create(self.name, robot)
        ipr = kernel.open_ns(robot.ns)
        try:
            with kernel.inside(robot.ns):
                # Before eth0 exists, so that it inherits the default: IPv4 only.
                kernel.set_sysctl("net.ipv6.conf.all.disable_ipv6", "1")
                kernel.set_sysctl("net.ipv6.conf.default.disable_ipv6", "1")
            self.medium.attach(robot.ns, robot.port, robot.mac)
            with kernel_errors(f"configuring eth0 of robot {robot.name}"):
                ipr.link("set", index=ipr.link_lookup(ifname="lo")[0], state="up")
                eth = ipr.link_lookup(ifname=naming.ROBOT_IFACE)[0]
                if self.addressing == "manual":
                    prefixlen = robot.address.network.prefixlen
                    ipr.addr("add", index=eth, address=robot.ip, prefixlen=prefixlen)
                ipr.link("set", index=eth, state="up")
                # Without a default route a namespace cannot send or join multicast.
                ipr.route("add", dst="224.0.0.0/4", oif=eth, scope=kernel.RT_SCOPE_LINK)
        finally:
            ipr.close()

    def add_robots(
        self, names: Iterable[str], positions: Mapping[str, Pos] | None = None
    ) -> list[Robot]:
        """Several robots, with the medium rules loaded once at the end."""
        with self.batch():
            return [self.add_robot(n, pos=(positions or {}).get(n, (0.0, 0.0))) for n in names]

    # -- the medium ----------------------------------------------------------------------

    @contextlib.contextmanager
    def batch(self) -> Iterator[None]:
        """Apply every medium change made in the body at once, at its end."""
        self._batch += 1
        ok = False
        try:
            yield
            ok = True
        finally:
            self._batch -= 1
            if self._batch == 0 and self._state == "up":
                if ok:
                    self._apply_medium()
                else:
                    with contextlib.suppress(NetlabError):
                        self._apply_medium()

    def _changed(self) -> None:
        if self._batch == 0:
            self._apply_medium()

    def _apply_medium(self) -> None:
        links = with_link_loss(self.topology.links(), self._nft_loss)
        self.medium.load(links, {r.name: r.port for r in self._robots.values()})

    def links(self) -> Links:
        """Ground truth: every (sender, receiver) pair that is linked now, with its loss in %.

        Includes each robot's own link loss (`shape(loss=...)`), however it is realised.
        """
        link_loss = {name: shape.loss for name, shape in self._shapes.items()}
        return with_link_loss(self.topology.links(), link_loss)

    def neighbours(self, ref: RobotRef) -> set[str]:
        """The robots `ref` hears now (ground truth)."""
        name = self.robot(ref).name
        return {a for (a, b) in self.links() if b == name}

    def live_addresses(self, ref: RobotRef) -> list[str]:
        """The IPv4 addresses eth0 has right now (with `addressing="auto"`, sdfrd's choice)."""
        robot = self.robot(ref)
        doing = f"reading the addresses of robot {robot.name}"
        return kernel.addresses(robot.ns, naming.ROBOT_IFACE, doing)

    def positions(self) -> dict[str, Pos]:
        return dict(self.topology.positions)

    def move(self, ref: RobotRef, pos: Pos) -> None:
        self._check_up()
        self.topology.move(self.robot(ref).name, pos)
        self._changed()

    def partition(self, groups: Iterable[Iterable[RobotRef]]) -> None:
        """Cut every link between `groups` (robots in none form one more group)."""
        self._check_up()
        self.topology.partition([[self.robot(r).name for r in g] for g in groups])
        self._changed()

    def merge(self) -> None:
        """End the partition."""
        self._check_up()
        self.topology.merge()
        self._changed()

    def set_pair_quality(
        self, a: RobotRef, b: RobotRef, *, loss: float | None, both: bool = True
    ) -> None:
        """Loss in % of a→b (and b→a if `both`) while linked; None: back to the range model."""
        self._check_up()
        self.topology.set_pair_quality(self.robot(a).name, self.robot(b).name, loss, both)
        self._changed()

    def run_mobility(
        self,
        model: MobilityModel,
        duration: float,
        step: float = 0.5,
        *,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> list[tuple[float, Links]]:
        """Move the model's robots every `step` seconds for `duration`; the links at each step."""
        self._check_up()
        for name in model.robots:
            self.robot(name)
        timeline: list[tuple[float, Links]] = []

        def apply(t: float, positions: dict[str, Pos]) -> None:
            with self.batch():
                for name, pos in positions.items():
                    self.topology.move(name, pos)
            timeline.append((t, self.links()))

        walk(model, duration, step, apply, clock=clock, sleep=sleep)
        return timeline

    # -- shaping -------------------------------------------------------------------------

    def shape(self, ref: RobotRef, **params: Any) -> LinkShape:
        """Shape the robot's link (both directions); no parameters removes all shaping.

        delay/jitter in ms, loss/duplicate/reorder/corrupt in %, rate in bit/s or
        '1mbit'. Raises ShapingUnsupported, before changing anything, for what this
        kernel cannot do.
        """
        self._check_up()
        robot = self.robot(ref)
        shape = LinkShape.of(**params)
        plan = shaping.plan(shape, capabilities())
        ipr = kernel.open_ns(robot.ns)
        try:
            eth = ipr.link_lookup(ifname=naming.ROBOT_IFACE)[0]
            shaping.apply(ipr, eth, plan, f"eth0 of {robot.name}")
        finally:
            ipr.close()
        shaping.apply(
            self.medium.ipr, self.medium.ifindex(robot.port), plan, f"the air port of {robot.name}"
        )
        self._shapes[robot.name] = shape
        if plan.nft_loss:
            self._nft_loss[robot.name] = plan.nft_loss
        else:
            self._nft_loss.pop(robot.name, None)
        self._changed()
        return shape

    def shape_of(self, ref: RobotRef) -> LinkShape:
        return self._shapes.get(self.robot(ref).name, LinkShape())

    # -- processes -----------------------------------------------------------------------

    def _record_proc(self, robot: Robot, pid: int, role: str, argv: Sequence[str]) -> None:
        assert self._record is not None
        self._record.processes = [p for p in self._record.processes if cleanup.running(p.pid)]
        self._record.processes.append(
            ProcRecord(pid, cleanup.start_time(pid) or 0, robot.name, role, list(argv))
        )
        self._save()

    def popen(self, ref: RobotRef, argv: Sequence[str], **kw: Any) -> subprocess.Popen[Any]:
        """Start `argv` inside the robot, in its own session; stopped when the lab goes down.

        Keyword arguments go to subprocess.Popen; stdin defaults to /dev/null.
        """
        self._check_up()
        robot = self.robot(ref)
        if "process_group" in kw or kw.get("start_new_session", True) is not True:
            raise ValueError("lab processes always run in a session of their own")
        kw.setdefault("stdin", subprocess.DEVNULL)
        kw["start_new_session"] = True  # one process group per process: stop/kill reach all of it
        full = self.kind(robot.runtime).exec_argv(robot, argv, stdin=_reads_stdin(kw))
        with kernel_errors(f"starting {argv[0] if argv else argv!r} in robot {robot.name}"):
            proc: subprocess.Popen[Any] = subprocess.Popen(full, **kw)
        self._procs.append(proc)
        self._record_proc(robot, proc.pid, "process", argv)
        return proc

    def exec(
        self, ref: RobotRef, argv: Sequence[str], **kw: Any
    ) -> subprocess.CompletedProcess[Any]:
        """Run `argv` inside the robot to completion (output captured as text, 30 s timeout).

        Inside a container robot it runs in the robot's container (its image's programs)."""
        self._check_up()
        robot = self.robot(ref)
        kw.setdefault("stdin", subprocess.DEVNULL)
        if "stdout" not in kw and "stderr" not in kw:
            kw.setdefault("capture_output", True)
        kw.setdefault("text", True)
        kw.setdefault("timeout", 30)
        full = self.kind(robot.runtime).exec_argv(robot, argv, stdin=_reads_stdin(kw))
        return subprocess.run(full, **kw)

    def sdfrd_options(self, ref: RobotRef, **options: Any) -> dict[str, Any]:
        """sdfrd's options for the robot by name: the lab's, updated with `options`."""
        robot = self.robot(ref)
        opts: dict[str, Any] = {
            "iface": naming.ROBOT_IFACE,
            "fleet": self.fleet,
            "robot_id": robot.name,
            "state_dir": robot.state_dir,
            "addressing": self.addressing,
        }
        opts.update(options)
        return opts

    def sdfrd_argv(self, ref: RobotRef, **options: Any) -> list[str]:
        """The command line of sdfrd as a host process in the robot's namespace (what a
        namespace robot runs): `options` are its flags (beacon_interval=0.5)."""
        return NamespaceKind().argv(self.sdfrd_options(ref, **options))

    def start(self, ref: RobotRef, *, timeout: float = START_TIMEOUT, **options: Any) -> None:
        """Run sdfrd in the robot and wait until its discovery layer is up."""
        robot = self.robot(ref)
        self._spawn(robot, options)
        self.wait_healthy(robot, timeout)

    def start_all(
        self, refs: Iterable[RobotRef] | None = None, *, timeout: float = 60.0, **options: Any
    ) -> None:
        """Start sdfrd on several robots (all by default) at once, then wait for all."""
        robots = [self.robot(r) for r in (refs if refs is not None else list(self._robots))]
        for robot in robots:
            self._spawn(robot, options)
        deadline = time.monotonic() + timeout
        for robot in robots:
            self.wait_healthy(robot, max(0.1, deadline - time.monotonic()))

    def _spawn(self, robot: Robot, options: dict[str, Any]) -> None:
        self._check_up()
        if self.alive(robot):
            raise LabStateError(f"sdfrd already runs on robot {robot.name}; stop it first")
        if len(str(robot.api_socket)) > SUN_PATH_MAX:
            raise NetlabError(
                f"{robot.api_socket} is longer than a unix socket path may be "
                f"({SUN_PATH_MAX} bytes): give the lab a shorter workdir"
            )
        with kernel_errors(f"creating {robot.state_dir}"):
            robot.state_dir.mkdir(parents=True, exist_ok=True)
        kind = self.kind(robot.runtime)
        started = kind.spawn(self.name, robot, self.sdfrd_options(robot, **options))
        self._daemons[robot.name] = started.daemon
        self._daemon_opts[robot.name] = dict(options)
        self._procs += started.helpers
        self._record_proc(robot, started.daemon.pid, "sdfrd", started.argv)
        for helper in started.helpers:
            self._record_proc(robot, helper.pid, "log", cast(list[str], helper.args))

    def wait_healthy(self, ref: RobotRef, timeout: float = START_TIMEOUT) -> None:
        """Wait until the robot's sdfrd reports discovery up; DaemonError (and stop it) if not."""
        robot = self.robot(ref)
        proc = self._daemons.get(robot.name)
        if proc is None:
            raise LabStateError(f"sdfrd was not started on robot {robot.name}")
        deadline = time.monotonic() + timeout
        last = "no answer yet"
        while True:
            code = proc.poll()
            if code is not None:
                raise DaemonError(
                    f"sdfrd on robot {robot.name} exited with {_status(code)} before it was "
                    f"healthy; {robot.log} ends with:\n{self.log_tail(robot)}"
                )
            if robot.api_socket.exists():
                try:
                    health = self.client(robot).health()
                    if health.get("discovery") == "up":
                        return
                    last = f"health {health}"
                except ApiError as exc:
                    last = str(exc)
            if time.monotonic() > deadline:
                self.kill(robot)
                raise DaemonError(
                    f"sdfrd on robot {robot.name} was not healthy within {timeout:.1f} s "
                    f"({last}); killed it. {robot.log} ends with:\n{self.log_tail(robot)}"
                )
            time.sleep(0.02)

    def alive(self, ref: RobotRef) -> bool:
        proc = self._daemons.get(self.robot(ref).name)
        return proc is not None and proc.poll() is None

    def daemon_pid(self, ref: RobotRef) -> int | None:
        """The pid of the robot's running sdfrd supervisor (its layers are its children)."""
        proc = self._daemons.get(self.robot(ref).name)
        return proc.pid if proc is not None and proc.poll() is None else None

    def stop(self, ref: RobotRef, timeout: float = STOP_TIMEOUT) -> int:
        """SIGTERM: a graceful stop (sdfrd says Byebye); its exit status."""
        robot = self.robot(ref)
        proc = self._running_daemon(robot)
        self._drop_client(robot)
        cleanup.signal_process(proc.pid, signal.SIGTERM)
        try:
            return proc.wait(timeout)
        except subprocess.TimeoutExpired:
            cleanup.signal_process(proc.pid, signal.SIGKILL)
            proc.wait()
            raise DaemonError(
                f"sdfrd on robot {robot.name} did not stop within {timeout} s of SIGTERM; "
                f"killed it. {robot.log} ends with:\n{self.log_tail(robot)}"
            ) from None

    def kill(self, ref: RobotRef) -> None:
        """SIGKILL to the daemon's whole process group: a silent departure, no Byebye."""
        robot = self.robot(ref)
        proc = self._running_daemon(robot)
        self._drop_client(robot)
        cleanup.signal_process(proc.pid, signal.SIGKILL)
        proc.wait()

    def restart(self, ref: RobotRef, *, timeout: float = START_TIMEOUT, **options: Any) -> None:
        """Stop (gracefully, if running) and start again; `options` update the last ones."""
        robot = self.robot(ref)
        if self.alive(robot):
            self.stop(robot)
        opts = {**self._daemon_opts.get(robot.name, {}), **options}
        self.start(robot, timeout=timeout, **opts)

    def _running_daemon(self, robot: Robot) -> Daemon:
        proc = self._daemons.get(robot.name)
        if proc is None or proc.poll() is not None:
            raise LabStateError(f"sdfrd is not running on robot {robot.name}")
        return proc

    def client(self, ref: RobotRef) -> Client:
        """A client of the robot's sdfrd over its unix socket (one per robot, reused)."""
        robot = self.robot(ref)
        if robot.name not in self._clients:
            self._clients[robot.name] = Client(unix_socket=robot.api_socket, timeout=2.0)
        return self._clients[robot.name]

    def _drop_client(self, robot: Robot) -> None:
        client = self._clients.pop(robot.name, None)
        if client is not None:
            client.close()

    def log_tail(self, ref: RobotRef, lines: int = 20) -> str:
        try:
            text = self.robot(ref).log.read_text(errors="replace")
        except OSError:
            return "(no log)"
        return "\n".join(text.splitlines()[-lines:])


def _reads_stdin(kw: Mapping[str, Any]) -> bool:
    """Whether a process started with Popen/run keywords `kw` is given a standard input."""
    return "input" in kw or kw.get("stdin") not in (None, subprocess.DEVNULL)


def _status(code: int) -> str:
    return f"signal {-code}" if code < 0 else f"status {code}"
