"""systemd's readiness and watchdog protocol (sd_notify), without libsystemd.

A service of `Type=notify` is given the path of a unix datagram socket in NOTIFY_SOCKET
(`@name` for the abstract namespace); the service sends it newline-separated assignments:
`READY=1` once it serves, `STATUS=...` for `systemctl status`, `WATCHDOG=1` at least every
WATCHDOG_USEC microseconds when the unit sets WatchdogSec=, and `STOPPING=1` on the way out.
Without NOTIFY_SOCKET (not under systemd) every call does nothing.
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import socket
import threading
from collections.abc import Callable

log = logging.getLogger("sdfrd")


def _address() -> str | None:
    path = os.environ.get("NOTIFY_SOCKET")
    if not path:
        return None
    if path.startswith("@"):  # the abstract namespace
        return "\0" + path[1:]
    return path


def notify(*assignments: str) -> bool:
    """Send `assignments` (e.g. "READY=1", "STATUS=serving") to systemd; False when not
    under a notify service manager, or when the message could not be sent (logged)."""
    address = _address()
    if address is None:
        return False
    message = "\n".join(assignments).encode()
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            sock.connect(address)
            sock.sendall(message)
    except OSError as exc:
        log.warning("cannot notify systemd at %s: %s", address.lstrip("\0"), exc)
        return False
    return True


def watchdog_interval() -> float | None:
    """Seconds within which systemd wants WATCHDOG=1 from this process (None: it does not)."""
    usec = os.environ.get("WATCHDOG_USEC", "")
    pid = os.environ.get("WATCHDOG_PID", "")
    if not usec.isdigit() or int(usec) == 0:
        return None
    if pid and (not pid.isdigit() or int(pid) != os.getpid()):
        return None  # meant for another process
    return int(usec) / 1_000_000


#: What the layers are told by the supervisor: the pipe to beat on.
HEARTBEAT_ENV = "SDFR_HEARTBEAT_FD"


class Stopper:
    """How a supervisor stops a layer that is one of its threads: the layer leaves a callback
    (`on_stop`), the supervisor calls `stop` from its own thread. A stop asked for before the
    layer left its callback runs the callback as soon as it is left."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._callbacks: list[Callable[[], None]] = []
        self.requested = False

    def add(self, callback: Callable[[], None]) -> None:
        with self._lock:
            self._callbacks.append(callback)
            now = self.requested
        if now:
            callback()

    def stop(self) -> None:
        with self._lock:
            self.requested = True
            callbacks = list(self._callbacks)
        for callback in callbacks:
            callback()


class _Host(threading.local):
    """What a layer that runs as a thread of sdfrd (`--layers threads`) is given by its
    supervisor instead of a process's environment and signals: the pipe to beat on, and its
    Stopper."""

    beat_fd: int | None = None
    stopper: Stopper | None = None


_host = _Host()


def host_thread(beat_fd: int, stopper: Stopper) -> None:
    """Make the calling thread a layer: `beat()` writes to `beat_fd`, and `on_stop` leaves
    its callback with `stopper`."""
    _host.beat_fd = beat_fd
    _host.stopper = stopper


def on_stop(loop: asyncio.AbstractEventLoop, callback: Callable[[], None]) -> None:
    """Run `callback` in `loop` when the layer is asked to stop: on SIGTERM or SIGINT for a
    layer that is a process of its own, on its supervisor's word for one that is a thread
    (signals reach only a process's main thread)."""
    stopper = _host.stopper
    if stopper is None:
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, callback)
        return

    def stop() -> None:
        loop.call_soon_threadsafe(callback)

    stopper.add(stop)


def beat() -> None:
    """A layer's heartbeat to its supervisor: one byte on the pipe it was given (nothing when
    it runs alone). The supervisor restarts a layer whose beats stop (a hung event loop, a
    SIGSTOP), which a process that is still there would never be otherwise."""
    fd = _host.beat_fd
    if fd is None:
        env = os.environ.get(HEARTBEAT_ENV, "")
        if not env.isdigit():
            return
        fd = int(env)
    try:
        os.write(fd, b".")
    except BlockingIOError:  # the supervisor is behind reading: it has news enough
        pass
    except OSError:  # the supervisor is gone (the kernel ends us too: PDEATHSIG)
        pass
