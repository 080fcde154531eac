"""`sdfrd`: resolves the configuration once, then runs and restarts the two layers.

The API layer and the discovery layer are separate processes so that either
can crash or be restarted while the other goes on; they share only the
store in the state directory. The supervisor restarts a layer that exits
without being asked to, with a growing back-off, and one whose heartbeat (a
byte a second on a pipe) stops for STALL_AFTER seconds: a hung or stopped
process is killed and started again. A layer that cannot start at all (exit
status 2: an address that is not this machine's, permission denied, a bad
configuration) ends sdfrd at once with status 2, since a restart cannot fix
it. It stops both layers on SIGTERM. If the supervisor itself is killed, the
kernel kills both layers (PR_SET_PDEATHSIG), so a `kill -9` of sdfrd is a
silent departure. Under systemd (Type=notify) it says READY=1 once both
layers beat, and sends the watchdog's WATCHDOG=1 (sdfr.daemon.notify).
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import json
import logging
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

from sdfr import keystore, netif, wifi
from sdfr.config import Config, from_args, to_args
from sdfr.daemon import logs, notify
from sdfr.errors import SdfrError
from sdfr.store import Store

log = logging.getLogger("sdfrd")

LAYERS = {"api": "sdfr.daemon.apiserver", "discovery": "sdfr.daemon.discovery"}
STOP_GRACE = 5.0
BACKOFF_MAX = 5.0
STABLE_AFTER = 30.0
#: A layer that has not beaten for this long (seconds) is hung or stopped: it is restarted.
STALL_AFTER = 10.0
#: Longest a layer may take from its start to its first heartbeat.
START_GRACE = 30.0
#: A layer's exit status for "cannot start; a restart will not help" (its message says why).
EXIT_CANNOT_START = 2
_PR_SET_PDEATHSIG = 1
LOCK_NAME = "sdfrd.lock"


def _die_with_parent() -> None:
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)


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
    module: str
    proc: subprocess.Popen[bytes] | None = None
    started: float = 0.0
    backoff: float = 0.2
    restart_at: float = 0.0
    restarts: int = 0
    #: The read end of the pipe the layer beats on, and when it last did (None: not yet).
    beats: int | None = None
    last_beat: float | None = None
    #: It beat at least once since sdfrd started: it can start.
    ever_up: bool = False


class Supervisor:
    def __init__(self, cfg: Config, lock_fd: int | None = None) -> None:
        self.cfg = cfg
        self.lock_fd = lock_fd
        self.args = to_args(cfg)
        self.layers = [Layer(name, module) for name, module in LAYERS.items()]
        self.stopping = False
        self.exit_status = 0
        self.pids_file = cfg.state_dir / "layers.json"
        self.ready = False
        self.watchdog = notify.watchdog_interval()
        self._next_watchdog = 0.0

    def spawn(self, layer: Layer) -> None:
        if layer.beats is not None:
            os.close(layer.beats)
        beats, beat_w = os.pipe2(os.O_CLOEXEC | os.O_NONBLOCK)
        env = {k: v for k, v in os.environ.items() if not k.startswith(("NOTIFY_", "WATCHDOG_"))}
        env[notify.HEARTBEAT_ENV] = str(beat_w)
        keep = (beat_w,) if self.lock_fd is None else (beat_w, self.lock_fd)
        try:
            layer.proc = subprocess.Popen(
                [sys.executable, "-m", layer.module, *self.args],
                preexec_fn=_die_with_parent,
                stdin=subprocess.DEVNULL,
                pass_fds=keep,
                env=env,
            )
        finally:
            os.close(beat_w)
        layer.beats = beats
        layer.last_beat = None
        layer.started = time.monotonic()
        log.info("%s layer started (pid %d)", layer.name, layer.proc.pid)
        self._write_pids()

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
            self.stopping = True

        signal.signal(signal.SIGTERM, on_signal)
        signal.signal(signal.SIGINT, on_signal)
        for layer in self.layers:
            self.spawn(layer)
        while not self.stopping:
            now = time.monotonic()
            for layer in self.layers:
                self._watch(layer, now)
            self._tell_systemd(now)
            time.sleep(0.05)
        return self.shutdown()

    def _tell_systemd(self, now: float) -> None:
        up = all(layer.proc is not None and layer.last_beat is not None for layer in self.layers)
        if up and not self.ready:
            self.ready = True
            notify.notify("READY=1", f"STATUS=serving the API on {self.cfg.api}")
        elif not up and self.ready:
            self.ready = False
            down = ", ".join(x.name for x in self.layers if x.proc is None or x.last_beat is None)
            notify.notify(f"STATUS=restarting the {down} layer")
        if self.watchdog is not None and now >= self._next_watchdog:
            notify.notify("WATCHDOG=1")
            self._next_watchdog = now + self.watchdog / 2

    def _read_beats(self, layer: Layer, now: float) -> None:
        if layer.beats is None:
            return
        try:
            if os.read(layer.beats, 4096):
                layer.last_beat = now
                layer.ever_up = True
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
                    log.warning(
                        "%s layer (pid %d) has not beaten for %.0f s (hung or stopped); "
                        "killing it to start it again",
                        layer.name,
                        proc.pid,
                        now - since,
                    )
                    proc.kill()  # (SIGKILL ends a stopped process too)
                    proc.wait()
                else:
                    return
            code = proc.returncode
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

    def shutdown(self) -> int:
        notify.notify("STOPPING=1")
        # Discovery first, so its Byebye goes out while the API still answers.
        for layer in reversed(self.layers):
            if layer.proc is not None and layer.proc.poll() is None:
                layer.proc.terminate()
        deadline = time.monotonic() + STOP_GRACE
        for layer in self.layers:
            if layer.proc is None:
                continue
            try:
                layer.proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s layer did not stop in %.0f s; killing it", layer.name, STOP_GRACE)
                layer.proc.kill()
                layer.proc.wait()
        self.pids_file.unlink(missing_ok=True)
        for layer in self.layers:
            if layer.beats is not None:
                os.close(layer.beats)
                layer.beats = None
        log.info("stopped")
        return self.exit_status


def main(argv: list[str] | None = None) -> int:
    logs.setup("sdfrd %(levelname)s %(message)s")
    try:
        cfg = resolve(from_args(argv))
        logging.getLogger().setLevel(cfg.log_level.upper())
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
        keyring = keystore.seed_keyring(cfg.state_dir, cfg.key_file, cfg.auth)
        log.info(
            "fleet %d: %s",
            cfg.fleet,
            f"keyed ({keyring.mode}, signing with {keyring.primary})"
            if keyring.keyed
            else "open (no key: datagrams are not authenticated)",
        )
        # Join the fleet's WiFi before the layers start; a wired interface, or wifi = off, or
        # no secret configured: the radio is left alone.
        wifi.setup(cfg)
    except SdfrError as exc:
        print(f"sdfrd: {exc}", file=sys.stderr)
        return 2
    return Supervisor(cfg, lock_fd).run()


if __name__ == "__main__":
    raise SystemExit(main())
