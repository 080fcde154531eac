"""What runs inside a lab's robots: sdfrd (its options checked as a `Config` before it
starts, waited for until healthy, stopped, killed, restarted, a client of its API) and any
other command (`popen`, `exec`).  `Lab` is made of this and `netlab.lab`'s life cycle,
robots and medium; every process is in the lab's manifest before the lab relies on it."""

from __future__ import annotations

import signal
import subprocess
import time
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

from netlab import cleanup
from netlab.errors import DaemonError, LabStateError, NetlabError, kernel_errors
from netlab.manifest import Manifest, ProcRecord
from netlab.robots import Daemon, NamespaceKind, Robot, RobotKind, RobotRef
from sdfr.client import Client
from sdfr.config.load import options_config
from sdfr.errors import ApiError, ConfigError

START_TIMEOUT = 20.0
STOP_TIMEOUT = 10.0
SUN_PATH_MAX = 107  # a unix socket path longer than this cannot be bound


class DaemonOptionError(NetlabError, ValueError):
    """sdfrd would refuse these options (a mistyped name, a value out of range); no daemon was
    started.  The message names the option, and the closest one for a typo."""


def check_options(robot: str, options: Mapping[str, Any]) -> None:
    """DaemonOptionError unless sdfrd on `robot` would take `options` (by name, None: unset)."""
    try:
        options_config(options)
    except ConfigError as exc:
        raise DaemonOptionError(f"sdfrd options of robot {robot}: {exc}") from None


class LabProcesses:
    """The processes of a `Lab` (a part of it: it needs the lab's robots, kinds and manifest)."""

    name: str
    fleet: int
    addressing: str
    air: str
    _record: Manifest | None
    _robots: dict[str, Robot]
    _daemons: dict[str, Daemon]
    _daemon_opts: dict[str, dict[str, Any]]
    _ended_by_lab: set[str]  # robots whose sdfrd the lab stopped or killed
    _procs: list[subprocess.Popen[Any]]
    _clients: dict[str, Client]

    if TYPE_CHECKING:

        def robot(self, ref: RobotRef) -> Robot: ...

        def kind(self, runtime: str) -> RobotKind: ...

        def _check_up(self) -> None: ...

        def _save(self) -> None: ...

        @property
        def wifi_secret_file(self) -> Path: ...

    # -- any command ---------------------------------------------------------------------

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

    # -- sdfrd ---------------------------------------------------------------------------

    def sdfrd_options(self, ref: RobotRef, **options: Any) -> dict[str, Any]:
        """sdfrd's options for the robot by name: the lab's, updated with `options`;
        DaemonOptionError (a typo, with the closest option) unless sdfrd would take them."""
        robot = self.robot(ref)
        opts: dict[str, Any] = {
            "iface": robot.iface,
            "fleet": self.fleet,
            "robot_id": robot.name,
            "state_dir": robot.state_dir,
            "addressing": self.addressing,
        }
        if self.air == "radio":  # sdfrd joins the fleet's WiFi on its radio (`wifi = auto`)
            opts["wifi_secret_file"] = self.wifi_secret_file
        opts.update(options)
        check_options(robot.name, opts)
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
            self.sdfrd_options(robot, **options)  # every robot's, before any starts
        for robot in robots:
            self._spawn(robot, options)
        deadline = time.monotonic() + timeout
        for robot in robots:
            self.wait_healthy(robot, max(0.1, deadline - time.monotonic()))

    def _spawn(self, robot: Robot, options: dict[str, Any]) -> None:
        opts = self.sdfrd_options(robot, **options)
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
        started = self.kind(robot.runtime).spawn(self.name, robot, opts)
        self._daemons[robot.name] = started.daemon
        self._ended_by_lab.discard(robot.name)
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

    def daemons_ended(self) -> dict[str, str]:
        """The robots whose sdfrd ended without the lab stopping or killing it, and how
        ("signal 9 (SIGKILL)", "status 1"): a daemon that crashed or that something else
        killed."""
        return {
            name: _status(code)
            for name, proc in self._daemons.items()
            if name not in self._ended_by_lab and (code := proc.poll()) is not None
        }

    def daemon_pid(self, ref: RobotRef) -> int | None:
        """The pid of the robot's running sdfrd supervisor (its layers are its children)."""
        proc = self._daemons.get(self.robot(ref).name)
        return proc.pid if proc is not None and proc.poll() is None else None

    def stop(self, ref: RobotRef, timeout: float = STOP_TIMEOUT) -> int:
        """SIGTERM: a graceful stop (sdfrd says Byebye); its exit status."""
        robot = self.robot(ref)
        proc = self._running_daemon(robot)
        self._drop_client(robot)
        self._ended_by_lab.add(robot.name)
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
        self._ended_by_lab.add(robot.name)
        cleanup.signal_process(proc.pid, signal.SIGKILL)
        proc.wait()

    def restart(self, ref: RobotRef, *, timeout: float = START_TIMEOUT, **options: Any) -> None:
        """Stop (gracefully, if running) and start again; `options` update the last ones."""
        robot = self.robot(ref)
        opts = {**self._daemon_opts.get(robot.name, {}), **options}
        self.sdfrd_options(robot, **opts)  # before the running one stops
        if self.alive(robot):
            self.stop(robot)
        self.start(robot, timeout=timeout, **opts)

    def _running_daemon(self, robot: Robot) -> Daemon:
        proc = self._daemons.get(robot.name)
        if proc is None or proc.poll() is not None:
            raise LabStateError(f"sdfrd is not running on robot {robot.name}")
        return proc

    # -- clients -------------------------------------------------------------------------

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

    def _close_clients(self) -> None:
        for client in self._clients.values():
            client.close()
        self._clients.clear()

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
    """An exit status as Popen gives it, in words: "status 1", "signal 9 (SIGKILL)"."""
    if code >= 0:
        return f"status {code}"
    try:
        return f"signal {-code} ({signal.Signals(-code).name})"
    except ValueError:
        return f"signal {-code}"
