"""`sdfrd`: resolves the configuration once, then runs and restarts the two layers.

The API layer and the discovery layer are separate processes so that either
can crash or be restarted while the other goes on; they share only the
store in the state directory. The supervisor restarts a layer that exits
without being asked to, with a growing back-off, and stops both on SIGTERM.
If the supervisor itself is killed, the kernel kills both layers
(PR_SET_PDEATHSIG), so a `kill -9` of sdfrd is a silent departure.
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
from sdfr.daemon import logs
from sdfr.errors import SdfrError
from sdfr.store import Store

log = logging.getLogger("sdfrd")

LAYERS = {"api": "sdfr.daemon.apiserver", "discovery": "sdfr.daemon.discovery"}
STOP_GRACE = 5.0
BACKOFF_MAX = 5.0
STABLE_AFTER = 30.0
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


class Supervisor:
    def __init__(self, cfg: Config, lock_fd: int | None = None) -> None:
        self.cfg = cfg
        self.lock_fd = lock_fd
        self.args = to_args(cfg)
        self.layers = [Layer(name, module) for name, module in LAYERS.items()]
        self.stopping = False
        self.pids_file = cfg.state_dir / "layers.json"

    def spawn(self, layer: Layer) -> None:
        layer.proc = subprocess.Popen(
            [sys.executable, "-m", layer.module, *self.args],
            preexec_fn=_die_with_parent,
            stdin=subprocess.DEVNULL,
            pass_fds=() if self.lock_fd is None else (self.lock_fd,),
        )
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
            time.sleep(0.05)
        return self.shutdown()

    def _watch(self, layer: Layer, now: float) -> None:
        proc = layer.proc
        if proc is not None:
            code = proc.poll()
            if code is None:
                if now - layer.started > STABLE_AFTER:
                    layer.backoff = 0.2
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
        log.info("stopped")
        return 0


def main(argv: list[str] | None = None) -> int:
    logs.setup("sdfrd %(levelname)s %(message)s")
    try:
        cfg = resolve(from_args(argv))
        logging.getLogger().setLevel(cfg.log_level.upper())
        Store(cfg.state_dir).close()  # a state directory we cannot use is reported once, here
        lock_fd = lock_state_dir(cfg.state_dir)
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
