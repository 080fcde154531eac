"""What crosses between the layers besides the store, defined once.

The two layers share the store (sdfr.store: the API layer writes the local services, the
discovery layer the history map, both the event log; the discovery layer also writes its
status file). Besides the store they speak over two unix datagram sockets in the state
directory, and each layer beats to the supervisor on a pipe:

- STATUS_SOCKET, bound by the API layer; the discovery layer sends it
  - its status record (`sdfr.records.status.DiscoveryStatus` as JSON) when it changed and
    when asked:
    the status and the discovery layer's liveness without touching the disk;
  - EVENTS when it stored new rows in the event log: GET /events reads them now.
- CONTROL_SOCKET, bound by the discovery layer; the API layer sends it
  - SERVICES when the local services or the keyring changed: they are announced now;
  - STATUS to ask for the status record now (before an answer shows it).
- The heartbeat pipe: a layer writes a byte on it (`Host.beat`) from its event loop; the
  supervisor restarts a layer whose beats stop. A layer is handed its `Host` (the pipe, and
  for a thread its `Stopper`) by the supervisor.

Every datagram is best effort: one that finds no listener is dropped, and each layer looks
for itself too (the discovery layer at its slow ticks, the API layer at the status file).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import socket
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import asyncio

#: (What only the API layer says: under its logger.)
log = logging.getLogger("sdfr.api")

#: The API layer's datagram socket in the state directory (discovery layer to API layer).
STATUS_SOCKET = "status.sock"
#: The discovery layer's datagram socket in the state directory (API layer to discovery).
CONTROL_SOCKET = "discovery.sock"

#: API layer to discovery layer: the local services (or the keyring) changed.
SERVICES = b"services\n"
#: API layer to discovery layer: send the status record now.
STATUS = b"status\n"
#: Discovery layer to API layer: new events in the store's event log. (Any other datagram
#: on STATUS_SOCKET is a status record.)
EVENTS = b"events\n"


# -- API layer to discovery layer ---------------------------------------------------------------


def notify_discovery(state_dir: Path, what: bytes = SERVICES) -> bool:
    """Wake the discovery layer so it announces a change of the local services at once (or,
    STATUS, sends its status now); whether the datagram went.

    Best effort: when discovery is down it is told nothing, and it polls the version anyway.
    """
    path = str(state_dir / CONTROL_SOCKET)
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.setblocking(False)
        try:
            sock.sendto(what, path)
        except (FileNotFoundError, ConnectionRefusedError, BlockingIOError):
            return False
        except OSError as exc:
            log.warning("cannot notify the discovery layer at %s: %s", path, exc)
            return False
    return True


def open_control(state_dir: Path) -> socket.socket:
    """The discovery layer's CONTROL_SOCKET, bound (a stale one replaced), not blocking."""
    path = state_dir / CONTROL_SOCKET
    path.unlink(missing_ok=True)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    os.chmod(path, 0o660)
    sock.setblocking(False)
    return sock


def close_control(sock: socket.socket, state_dir: Path) -> None:
    sock.close()
    (state_dir / CONTROL_SOCKET).unlink(missing_ok=True)


def status_asked(sock: socket.socket) -> bool:
    """Read what waits on CONTROL_SOCKET: True when the status was asked for (STATUS), else
    it was SERVICES."""
    asked = False
    while True:
        try:
            asked |= sock.recv(64).startswith(STATUS.rstrip())
        except OSError:  # nothing more to read now (BlockingIOError), or an error
            return asked


# -- discovery layer to API layer ---------------------------------------------------------------


class ToApi:
    """The discovery layer's sender to STATUS_SOCKET (one socket, kept open)."""

    def __init__(self, state_dir: Path) -> None:
        self.path = str(state_dir / STATUS_SOCKET)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.setblocking(False)

    def send(self, message: bytes) -> None:
        """A status record (JSON) or EVENTS; nothing when no API layer listens (it polls)."""
        with contextlib.suppress(OSError):
            self.sock.sendto(message, self.path)


def receive(sock: socket.socket, peek: bytearray) -> Iterator[bytes]:
    """Each datagram waiting on `sock` (the API layer's STATUS_SOCKET), read at its own size
    (peeked with MSG_TRUNC into the one byte of `peek`): a large fixed buffer would be
    allocated and freed whole at every read."""
    while True:
        try:
            size = sock.recv_into(peek, 1, socket.MSG_PEEK | socket.MSG_TRUNC)
            data = sock.recv(max(size, 1))
        except OSError:  # nothing more to read now (or the socket went away)
            return
        yield data


# -- the supervisor and its layers --------------------------------------------------------------


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


#: The heartbeat pipe's bytes: a layer alive, and serving or still starting.
SERVING = b"."
STARTING = b","


class Host:
    """What a layer is given by its supervisor: the pipe to beat on (None: it runs alone), and,
    for a layer that is a thread of sdfrd (`--layers threads`), its Stopper instead of the
    signals that reach only a process's main thread."""

    def __init__(self, beat_fd: int | None = None, stopper: Stopper | None = None) -> None:
        self.beat_fd = beat_fd
        self.stopper = stopper

    def beat(self, starting: bool = False) -> None:
        """A heartbeat to the supervisor: one byte on the pipe, STARTING while the layer is
        alive but not yet serving (the discovery layer before it speaks on the fleet's
        network), SERVING after. The supervisor restarts a layer whose beats stop (a hung
        event loop, a SIGSTOP), which a process that is still there would never be
        otherwise, and tells systemd READY=1 once every layer serves."""
        if self.beat_fd is None:
            return
        try:
            os.write(self.beat_fd, STARTING if starting else SERVING)
        except BlockingIOError:  # the supervisor is behind reading: it has news enough
            pass
        except OSError:  # the supervisor is gone (the kernel ends us too: PDEATHSIG)
            pass

    def on_stop(self, loop: asyncio.AbstractEventLoop, callback: Callable[[], None]) -> None:
        """Run `callback` in `loop` when the layer is asked to stop: on SIGTERM or SIGINT for
        a layer that is a process of its own, on its supervisor's word for a thread."""
        stopper = self.stopper
        if stopper is None:
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.add_signal_handler(sig, callback)
            return

        def stop() -> None:
            loop.call_soon_threadsafe(callback)

        stopper.add(stop)
