"""`sdfrd`: resolves the configuration once, then runs and restarts the two layers.

By default (`--layers threads`) the API layer and the discovery layer are two
threads of this process, each running its own event loop, sharing only the
store in the state directory: one interpreter and one copy of the code, less
memory than processes. A layer whose main ends (an exception, a bad start)
is started again alone, in a new thread, while the other serves. A hung layer
(its beats stop) cannot be killed alone: the supervisor stops the other one
and starts sdfrd again in the same process (exec), its state kept.

With `--layers processes` they are separate processes so that either can be killed, crash
or hang while the other goes on. The supervisor imports both layers' code once and forks
each layer from itself (no exec): the interpreter and every module the layers load are
then one set of pages shared by the three processes (`gc.freeze` keeps the collector from
writing to them), so the tree costs little more than one process, and a restart is a fork,
not a new interpreter. The supervisor itself runs no event loop and opens no database
while the layers run: it sleeps in `select` until a layer's first beat, a child's exit, a
signal, or its next check (a few seconds away), so it stays the one part that nothing can
hang. The supervisor restarts a layer that exits without being asked to, with a growing
back-off, and one whose heartbeat (a byte on a pipe at each of its ticks:
sdfr.daemon.channel.Host) stops for STALL_AFTER seconds: a hung or stopped process is
killed and started again. A layer that cannot start at all (exit status 2: an address that
is not this machine's, permission denied, a bad configuration) ends sdfrd at once with
status 2, since a restart cannot fix it. It stops both layers on SIGTERM. If the
supervisor itself is killed, the kernel kills both layers (PR_SET_PDEATHSIG), so a
`kill -9` of sdfrd is a silent departure. A crash in native code (SIGSEGV, SIGABRT, SIGBUS,
SIGFPE, SIGILL) leaves each thread's stack in the log (faulthandler). Under systemd
(Type=notify) it says READY=1 once both layers serve (the discovery layer beats
"starting" until it speaks on the fleet's network), and sends the watchdog's WATCHDOG=1
(sdfr.daemon.notify).
"""

from __future__ import annotations

import contextlib
import errno
import faulthandler
import fcntl
import gc
import importlib
import json
import logging
import os
import select
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

from sdfr.config import keystore
from sdfr.config.load import Config, from_args, to_args
from sdfr.daemon import logs, notify
from sdfr.daemon.channel import SERVING, Host, Stopper
from sdfr.errors import SdfrError
from sdfr.host import netif, procfs, wifi
from sdfr.store import Store

log = logging.getLogger("sdfrd")

LAYERS = {"api": "sdfr.daemon.apiserver", "discovery": "sdfr.daemon.discovery"}
#: When set (a directory), each layer runs under cProfile and writes
#: DIR/<layer>-<pid>.pstats when it ends: where a layer's CPU goes (bench.footprint uses it).
PROFILE_ENV = "SDFR_PROFILE"
#: How often (seconds) the supervisor looks at beats it has not been woken for.
CHECK_EVERY = 5.0
STOP_GRACE = 5.0
BACKOFF_MAX = 5.0
STABLE_AFTER = 30.0
#: A layer that has not beaten for this long (seconds) is hung or stopped: it is restarted
#: (three of its beats: a loop a loaded machine holds back for a few seconds is not hung).
STALL_AFTER = 15.0
#: Longest a layer may take from its start to its first heartbeat.
START_GRACE = 30.0
#: A layer's exit status for "cannot start; a restart will not help" (its message says why).
EXIT_CANNOT_START = 2
LOCK_NAME = "sdfrd.lock"

#: A layer's entry point: its flags and its Host in, its exit status out.
Main = Callable[[list[str], Host], int]


def _set_comm(name: str) -> None:
    """Name the calling thread (a process's main thread names the process) in ps and
    /proc/PID/comm, as prctl(PR_SET_NAME) does, without loading ctypes (which threads mode
    never needs otherwise)."""
    with contextlib.suppress(OSError):
        Path(f"/proc/self/task/{threading.get_native_id()}/comm").write_text(name)


def preload() -> dict[str, Main]:
    """Import both layers now, so that the forked layers share these pages, and move what
    exists to the collector's permanent generation (no collection writes to them)."""
    mains: dict[str, Main] = {
        name: importlib.import_module(module).main for name, module in LAYERS.items()
    }
    gc.collect()
    gc.freeze()
    return mains


def _run_main(layer: Layer, args: list[str], host: Host) -> int:
    """The layer's main, under cProfile when PROFILE_ENV names a directory."""
    where = os.environ.get(PROFILE_ENV)
    if not where:
        return layer.main(args, host)
    import cProfile

    profile = cProfile.Profile()
    try:
        return profile.runcall(layer.main, args, host)
    finally:
        profile.dump_stats(str(Path(where) / f"{layer.name}-{os.getpid()}.pstats"))


class Child:
    """A forked layer: its pid and, once reaped, its exit status (negative: the signal)."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            try:
                pid, status = os.waitpid(self.pid, os.WNOHANG)
            except ChildProcessError:  # reaped elsewhere: its status is lost
                self.returncode = 1
                return self.returncode
            if pid:
                self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while (code := self.poll()) is None:
            if deadline is not None and time.monotonic() >= deadline:
                raise TimeoutError(f"pid {self.pid} still runs")
            time.sleep(0.02)
        return code

    def signal(self, signum: int) -> None:
        if self.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signum)

    def kill(self) -> None:
        self.signal(signal.SIGKILL)

    def terminate(self) -> None:
        self.signal(signal.SIGTERM)


class LayerThread:
    """A layer run as a thread of this process (`--layers threads`), seen as a Child is: its
    exit status once its main returned. It has no `kill`: a hung thread ends only with the
    whole process (Supervisor.restart_daemon)."""

    def __init__(self, layer: Layer, target: Callable[[Stopper], int]) -> None:
        self.pid = os.getpid()
        self.returncode: int | None = None
        self.stopper = Stopper()
        self._done = threading.Event()
        self._thread = threading.Thread(
            target=self._run, args=(target,), name=f"sdfrd-{layer.name}", daemon=True
        )
        self._thread.start()

    def _run(self, target: Callable[[Stopper], int]) -> None:
        try:
            self.returncode = target(self.stopper)
        finally:
            self.returncode = 1 if self.returncode is None else self.returncode
            self._done.set()

    def poll(self) -> int | None:
        return self.returncode if self._done.is_set() else None

    def wait(self, timeout: float | None = None) -> int:
        if not self._done.wait(timeout):
            raise TimeoutError(f"the {self._thread.name} thread still runs")
        assert self.returncode is not None
        return self.returncode

    def terminate(self) -> None:
        self.stopper.stop()


def resolve(cfg: Config) -> Config:
    """Fill in what defaults to the machine (interface, robot id) and check it exists."""
    iface = cfg.iface or netif.default_iface()
    if not netif.exists(iface):
        raise SdfrError(f"iface: no interface named {iface!r} (see `ip link`)")
    robot_id = cfg.robot_id or netif.robot_id_from_mac(iface)
    return replace(cfg, iface=iface, robot_id=robot_id)


def lock_state_dir(state_dir: Path) -> int:
    """Hold STATE_DIR/sdfrd.lock for as long as this daemon runs; its file descriptor.

    Two daemons on one state directory would fight over its registrations and history. The
    layers inherit the descriptor, so the lock is held until the last process is gone.
    """
    path = state_dir / LOCK_NAME
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise SdfrError(f"state_dir: cannot open {path}: {exc.strerror or exc}") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
        os.close(fd)
        if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN):
            raise SdfrError(
                f"state_dir {state_dir} is in use by another sdfrd (pid {holder}); give each "
                "daemon its own --state-dir"
            ) from None
        raise SdfrError(f"state_dir: cannot lock {path}: {exc.strerror or exc}") from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd


@dataclass
class Layer:
    name: str
    main: Main
    proc: Child | LayerThread | None = None
    started: float = 0.0
    backoff: float = 0.2
    restart_at: float = 0.0
    restarts: int = 0
    #: The read end of the pipe the layer beats on, and when it last did (None: not yet).
    beats: int | None = None
    last_beat: float | None = None
    #: It beat at least once since sdfrd started: it can start.
    ever_up: bool = False
    #: It said it serves (SERVING on its pipe) since it was started.
    serving: bool = False


class Supervisor:
    def __init__(
        self, cfg: Config, lock_fd: int | None = None, mains: dict[str, Main] | None = None
    ) -> None:
        self.cfg = cfg
        self.lock_fd = lock_fd
        self.args = to_args(cfg)
        mains = preload() if mains is None else mains
        self.layers = [Layer(name, mains[name]) for name in LAYERS]
        # Signals and children's exits wake the select loop through this pipe.
        self._wake_r, self._wake_w = os.pipe2(os.O_CLOEXEC | os.O_NONBLOCK)
        self.stopping = False
        self.exit_status = 0
        self.pids_file = cfg.state_dir / "layers.json"
        self.ready = False
        self.watchdog = notify.watchdog_interval()
        self._next_watchdog = 0.0

    def spawn(self, layer: Layer) -> None:
        if layer.beats is not None:
            os.close(layer.beats)
            layer.beats = None
        beats, beat_w = os.pipe2(os.O_CLOEXEC | os.O_NONBLOCK)
        sys.stdout.flush()
        sys.stderr.flush()
        if self.cfg.layers == "threads":
            layer.proc = LayerThread(
                layer, lambda stopper: self._run_thread(layer, beat_w, stopper)
            )
            pid = layer.proc.pid
        else:
            pid = os.fork()
            if pid == 0:  # the layer
                os._exit(self._run_layer(layer, beats, beat_w))
            os.close(beat_w)
            layer.proc = Child(pid)
        layer.beats = beats
        layer.last_beat = None
        layer.serving = False
        layer.started = time.monotonic()
        # (Each layer's line a kind of its own: the log's RepeatFilter holds back a repeat.)
        log.info(
            f"{layer.name} layer started (%s)",
            "a thread" if isinstance(layer.proc, LayerThread) else f"pid {pid}",
        )
        self._write_pids()

    def _run_layer(self, layer: Layer, beats: int, beat_w: int) -> int:
        """In the forked child: become the layer, run it, its exit status (never returns to
        the supervisor's loop: the caller exits with it)."""
        code = 1
        try:
            procfs.die_with_parent()
            _set_comm(procfs.LAYER_COMM[layer.name])
            signal.set_wakeup_fd(-1)
            for signum in (signal.SIGTERM, signal.SIGINT, signal.SIGCHLD):
                signal.signal(signum, signal.SIG_DFL)
            # What is the supervisor's alone: the other layers' pipes, its wake-up pipe.
            for fd in [beats, self._wake_r, self._wake_w, *(x.beats for x in self.layers)]:
                if fd is not None:
                    os.close(fd)
            for x in self.layers:
                x.beats = None
            devnull = os.open(os.devnull, os.O_RDONLY)
            os.dup2(devnull, 0)
            os.close(devnull)
            for key in [k for k in os.environ if k.startswith(("NOTIFY_", "WATCHDOG_"))]:
                del os.environ[key]
            root = logging.getLogger()
            for handler in root.handlers[:]:  # the layer sets up its own format
                root.removeHandler(handler)
            code = _run_main(layer, list(self.args), Host(beat_w))
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 1
        except BaseException:
            traceback.print_exc()
        finally:
            with contextlib.suppress(Exception):
                logging.shutdown()
                sys.stdout.flush()
                sys.stderr.flush()
        return code

    def _run_thread(self, layer: Layer, beat_w: int, stopper: Stopper) -> int:
        """In the layer's thread: run it, its exit status (the thread then ends)."""
        code = 1
        try:
            _set_comm(procfs.LAYER_COMM[layer.name])
            code = _run_main(layer, list(self.args), Host(beat_w, stopper))
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 1
        except BaseException:
            log.exception("%s layer failed", layer.name)
        finally:
            with contextlib.suppress(OSError):
                os.close(beat_w)
        return code

    def restart_daemon(self, hung: Layer, silent: float) -> None:
        """A layer thread that hangs cannot be killed alone: stop the others (discovery says
        its byebye), then start sdfrd again in this process (exec: the same pid, the state
        dir kept; the descriptors, the lock's among them, close on exec)."""
        log.error(
            "%s layer has not beaten for %.0f s (hung); a thread cannot be killed alone: "
            "restarting sdfrd",
            hung.name,
            silent,
        )
        self._stop_layers([layer for layer in self.layers if layer is not hung])
        self.pids_file.unlink(missing_ok=True)
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os.execv(sys.executable, [sys.executable, *sys.orig_argv[1:]])

    def _write_pids(self) -> None:
        pids = {
            layer.name: layer.proc.pid
            for layer in self.layers
            if layer.proc is not None and layer.proc.poll() is None
        }
        pids["supervisor"] = os.getpid()
        tmp = self.pids_file.with_suffix(".tmp")
        tmp.write_text(json.dumps(pids))
        tmp.replace(self.pids_file)

    def run(self) -> int:
        def on_signal(signum: int, frame: object) -> None:
            if signum != signal.SIGCHLD:
                self.stopping = True

        signal.set_wakeup_fd(self._wake_w, warn_on_full_buffer=False)
        signal.signal(signal.SIGTERM, on_signal)
        signal.signal(signal.SIGINT, on_signal)
        signal.signal(signal.SIGCHLD, on_signal)
        for layer in self.layers:
            self.spawn(layer)
        while not self.stopping:
            now = time.monotonic()
            for layer in self.layers:
                self._watch(layer, now)
            self._tell_systemd(now)
            if self.stopping:
                break
            self._sleep(now)
        signal.set_wakeup_fd(-1)
        return self.shutdown()

    def _sleep(self, now: float) -> None:
        """Until something needs looking at: a signal (a child's exit, SIGTERM), the first
        beat of a layer not up yet, a restart or a systemd watchdog ping due, or CHECK_EVERY.
        A layer that is up is not listened to: its beats wait in the pipe until the next
        look, so steady beating wakes the supervisor once a CHECK_EVERY, not once a beat."""
        wait = [self._wake_r]
        until = now + CHECK_EVERY
        for layer in self.layers:
            if layer.proc is None:
                until = min(until, layer.restart_at)
            elif not layer.serving and layer.beats is not None:
                wait.append(layer.beats)
        if self.watchdog is not None:
            until = min(until, self._next_watchdog)
        ready, _, _ = select.select(wait, [], [], max(0.0, until - now))
        if self._wake_r in ready:
            with contextlib.suppress(BlockingIOError):
                os.read(self._wake_r, 4096)

    def _tell_systemd(self, now: float) -> None:
        up = all(layer.proc is not None and layer.serving for layer in self.layers)
        if up and not self.ready:
            self.ready = True
            notify.notify("READY=1", f"STATUS=serving the API on {self.cfg.api}")
        elif not up and self.ready:
            self.ready = False
            down = ", ".join(x.name for x in self.layers if x.proc is None or not x.serving)
            notify.notify(f"STATUS=restarting the {down} layer")
        if self.watchdog is not None and now >= self._next_watchdog:
            notify.notify("WATCHDOG=1")
            self._next_watchdog = now + self.watchdog / 2

    def _read_beats(self, layer: Layer, now: float) -> None:
        if layer.beats is None:
            return
        try:
            beats = os.read(layer.beats, 4096)
            if beats:
                layer.last_beat = now
                layer.ever_up = True
                layer.serving = layer.serving or SERVING in beats
        except BlockingIOError:
            pass

    def _watch(self, layer: Layer, now: float) -> None:
        proc = layer.proc
        if proc is not None:
            self._read_beats(layer, now)
            code = proc.poll()
            if code is None:
                if now - layer.started > STABLE_AFTER:
                    layer.backoff = 0.2
                since = layer.last_beat if layer.last_beat is not None else layer.started
                limit = STALL_AFTER if layer.last_beat is not None else START_GRACE
                if now - since > limit:
                    if isinstance(proc, LayerThread):  # (it cannot be killed alone)
                        self.restart_daemon(layer, now - since)
                        return
                    log.warning(
                        "%s layer (pid %d) has not beaten for %.0f s (hung or stopped); "
                        "killing it to start it again",
                        layer.name,
                        proc.pid,
                        now - since,
                    )
                    proc.kill()  # (SIGKILL ends a stopped process too)
                    code = proc.wait()
                else:
                    return
            if code == EXIT_CANNOT_START and not layer.ever_up:
                log.error(
                    "%s layer cannot start (its error is above); a restart would not fix "
                    "it: stopping",
                    layer.name,
                )
                self.exit_status = EXIT_CANNOT_START
                self.stopping = True
                layer.proc = None
                return
            log.warning(
                "%s layer exited (%s); restarting in %.1f s",
                layer.name,
                f"signal {-code}" if code < 0 else f"code {code}",
                layer.backoff,
            )
            layer.proc = None
            layer.restart_at = now + layer.backoff
            layer.backoff = min(BACKOFF_MAX, layer.backoff * 2)
            self._write_pids()
            return
        if now >= layer.restart_at:
            layer.restarts += 1
            self.spawn(layer)

    def _stop_layers(self, layers: list[Layer]) -> list[Layer]:
        """Ask `layers` to stop and wait for them, STOP_GRACE in all; those still running.
        Discovery first, so its Byebye goes out while the API still answers."""
        for layer in reversed(layers):
            if layer.proc is not None and layer.proc.poll() is None:
                layer.proc.terminate()
        deadline = time.monotonic() + STOP_GRACE
        late = []
        for layer in layers:
            if layer.proc is not None:
                try:
                    layer.proc.wait(max(0.0, deadline - time.monotonic()))
                except TimeoutError:
                    late.append(layer)
        return late

    def shutdown(self) -> int:
        notify.notify("STOPPING=1")
        for layer in self._stop_layers(self.layers):
            log.warning("%s layer did not stop in %.0f s; killing it", layer.name, STOP_GRACE)
            if isinstance(layer.proc, Child):  # (a thread ends with the process)
                layer.proc.kill()
                layer.proc.wait()
        self.pids_file.unlink(missing_ok=True)
        for layer in self.layers:
            if layer.beats is not None:
                os.close(layer.beats)
                layer.beats = None
        os.close(self._wake_r)
        os.close(self._wake_w)
        log.info("stopped")
        return self.exit_status


def main(argv: list[str] | None = None) -> int:
    # A crash in native code (a segfault, an abort) writes every thread's Python stack to
    # stderr (the log) before the process dies, instead of ending it without a line. (A stderr
    # that is no file, or closed, has nowhere to write it.)
    with contextlib.suppress(OSError, ValueError):
        faulthandler.enable(all_threads=True)
    logs.setup("sdfrd")
    try:
        cfg = from_args(argv)
        logs.setup("sdfrd", cfg.log_level, cfg.log_format)
        cfg = resolve(cfg)
        if cfg.layers == "threads":
            logs.share_with_threads()
        store = Store(cfg.state_dir)  # a state directory we cannot use is reported once, here
        lock_fd = lock_state_dir(cfg.state_dir)
        try:
            # Leases that ran out while sdfrd was down end before discovery could announce them.
            gone = store.expire_overdue(time.time())
            if gone:
                store.sync()
                log.info("leases ran out while sdfrd was down: withdrew %s", ", ".join(gone))
        finally:
            store.close()
        keyring = keystore.seed_keyring(
            cfg.state_dir, cfg.key_file, cfg.auth, wifi.datagram_key_source(cfg)
        )
        log.info(
            "fleet %d: %s",
            cfg.fleet,
            f"keyed ({keyring.mode}, signing with {keyring.primary if keyring.signs else 'none'})"
            if keyring.keyed
            else "open (no key: datagrams are not authenticated)",
        )
        # Join the fleet's WiFi before the layers start; a wired interface, or wifi = off, or
        # no secret configured: the radio is left alone.
        wifi.setup(cfg)
        if cfg.layers == "processes":
            importlib.import_module("ctypes")  # (die_with_parent's, before the fork: shared)
        mains = preload()
    except SdfrError as exc:
        print(f"sdfrd: {exc}", file=sys.stderr)
        return 2
    return Supervisor(cfg, lock_fd, mains).run()


if __name__ == "__main__":
    raise SystemExit(main())
