"""The API layer: the REST API (TCP and STATE_DIR/api.sock), and the listener of the discovery
layer's datagrams.

Started by the supervisor with the same flags as `sdfrd`; it lives and dies independently of
the discovery layer and shares state with it through the store and sdfr.daemon.channel.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import os
import resource
import secrets
import socket
import sys
from pathlib import Path

from sdfr.api import STATE, ApiState, Runner, TCPSite, UnixSite, create_app
from sdfr.config.load import Config, from_args, split_hostport
from sdfr.daemon import channel, logs
from sdfr.daemon.channel import Host
from sdfr.errors import ConfigError
from sdfr.store import Store, StoreError

log = logging.getLogger("sdfr.apiserver")

PREFIX = "sdfrd[api]"
#: Longest a stop waits for requests in flight (they take milliseconds).
SHUTDOWN_TIMEOUT = 5.0
#: sockaddr_un's sun_path holds 108 bytes, the terminating NUL included.
MAX_UNIX_PATH = 107
#: Who may open the API's and the status sockets: the daemon's user and the state
#: directory's group (docs/deploy.md).
SOCKET_MODE = 0o660


class StartError(Exception):
    """A listener cannot be opened; the message names the flag or path to fix."""


def api_socket_path(state_dir: Path) -> Path:
    return state_dir / "api.sock"


def _bind_error(flag: str, value: str, exc: OSError) -> StartError:
    reason = exc.strerror or str(exc)
    if exc.errno == errno.EADDRINUSE:
        reason = "address already in use (another sdfrd, or another program, listens there)"
    return StartError(f"--{flag} {value}: cannot listen: {reason}")


def _clear_stale_socket(path: Path) -> None:
    """Remove a socket left by a crashed API layer; refuse to steal one that answers."""
    if len(os.fsencode(path)) > MAX_UNIX_PATH:
        raise StartError(
            f"{path}: longer than the {MAX_UNIX_PATH} bytes a unix socket path may have; "
            "use a shorter --state-dir"
        )
    if not path.exists() and not path.is_symlink():
        return
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        probe.settimeout(0.5)
        try:
            probe.connect(str(path))
        except OSError:
            path.unlink(missing_ok=True)
            return
    raise StartError(f"{path}: another API layer is serving this state directory")


def bind_private(path: Path, kind: socket.SocketKind, mode: int = SOCKET_MODE) -> socket.socket:
    """A unix socket bound at `path` with `mode`, which no one ever sees there with another
    mode: it is bound in a new private (0700) directory beside `path`, given its mode, then
    renamed into place. (Binding in place creates it with the mode the umask leaves until a
    chmod follows; setting the umask around the bind would change it for the other layer's
    thread too.) OSError when it cannot be."""
    hidden = path.parent / f".s{secrets.token_hex(4)}"
    staged = hidden / "s"
    if len(os.fsencode(staged)) > MAX_UNIX_PATH:
        raise StartError(
            f"{path}: the state directory's path is too long for a unix socket in it "
            f"({MAX_UNIX_PATH} bytes, with {len(os.fsencode(staged)) - len(os.fsencode(path))} "
            "to spare); use a shorter --state-dir"
        )
    os.mkdir(hidden, 0o700)
    sock = socket.socket(socket.AF_UNIX, kind)
    try:
        sock.bind(str(staged))
        os.chmod(staged, mode)
        os.rename(staged, path)
    except BaseException:
        sock.close()
        with contextlib.suppress(OSError):
            staged.unlink()
        raise
    finally:
        with contextlib.suppress(OSError):
            hidden.rmdir()
    return sock


async def _start_tcp(runner: Runner, flag: str, value: str) -> None:
    host, port = split_hostport(flag, value)
    try:
        await TCPSite(runner, host, port).start()
    except OSError as exc:
        raise _bind_error(flag.replace("_", "-"), value, exc) from None


async def serve(cfg: Config, store: Store, stop: asyncio.Event, host: Host | None = None) -> None:
    """Serve until `stop` is set, beating on `host`'s pipe."""
    access_log = logging.getLogger("sdfr.api.access") if cfg.log_level == "debug" else None
    app = create_app(cfg, store)
    runner = Runner(app, access_log=access_log, shutdown_timeout=SHUTDOWN_TIMEOUT)
    sock_path = api_socket_path(cfg.state_dir)
    status = _StatusListener(cfg.state_dir / channel.STATUS_SOCKET, app[STATE])
    sock_bound = False
    try:
        await runner.setup()
        await _start_tcp(runner, "api", cfg.api)
        _clear_stale_socket(sock_path)
        try:
            listening = bind_private(sock_path, socket.SOCK_STREAM)
            sock_bound = True
            await UnixSite(runner, str(sock_path), sock=listening).start()
        except OSError as exc:
            raise StartError(f"{sock_path}: cannot listen: {exc.strerror or exc}") from None
        status.start()
        log.info("serving the API on http://%s and %s", cfg.api, sock_path)
        beating = asyncio.get_running_loop().create_task(_beat(host or Host()))
        await stop.wait()
        beating.cancel()
        log.info("stopping")
    finally:
        status.stop()
        await runner.cleanup()
        if sock_bound:
            with contextlib.suppress(OSError):
                sock_path.unlink()


#: The layer's tick (seconds): its beat to the supervisor, three within its STALL_AFTER.
BEAT_PERIOD = 5.0


async def _beat(host: Host) -> None:
    """The heartbeat the supervisor watches: from the event loop, so a hung loop stops it."""
    while True:
        host.beat()
        await asyncio.sleep(BEAT_PERIOD)


class _StatusListener:
    """Receives the discovery layer's status datagrams (its heartbeat, needing no disk)."""

    def __init__(self, path: Path, state: ApiState) -> None:
        self.path = path
        self.state = state
        self.sock: socket.socket | None = None
        self._peek = bytearray(1)

    def start(self) -> None:
        self.path.unlink(missing_ok=True)
        try:
            sock = bind_private(self.path, socket.SOCK_DGRAM)
        except (OSError, StartError) as exc:  # (a full disk: the status file is read instead)
            log.warning("cannot listen for the discovery layer's status on %s: %s", self.path, exc)
            return
        sock.setblocking(False)
        asyncio.get_running_loop().add_reader(sock.fileno(), self._read)
        self.sock = sock
        # The discovery layer sends its status when it changes or is asked: ask for it now.
        channel.notify_discovery(self.path.parent, channel.STATUS)

    def _read(self) -> None:
        assert self.sock is not None
        for data in channel.receive(self.sock, self._peek):
            self.state.take_status(data)

    def stop(self) -> None:
        if self.sock is not None:
            asyncio.get_running_loop().remove_reader(self.sock.fileno())
            self.sock.close()
            self.sock = None
            self.path.unlink(missing_ok=True)


def raise_fd_limit() -> None:
    """Use the hard limit of open files, not the soft one (1,024 on many systems): the local
    API must not run out of descriptors while programs hold connections to it."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    want = hard if hard != resource.RLIM_INFINITY else 65536
    if soft < want:
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(resource.RLIMIT_NOFILE, (want, hard))


async def _run(cfg: Config, store: Store, host: Host) -> None:
    stop = asyncio.Event()
    host.on_stop(asyncio.get_running_loop(), stop.set)
    await serve(cfg, store, stop, host)


def _fail(message: str) -> int:
    print(f"{PREFIX}: error: {message}", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None, host: Host | None = None) -> int:
    """The API layer (`host`: what its supervisor gave it; None: it runs alone)."""
    try:
        cfg = from_args(argv)
    except ConfigError as exc:
        return _fail(str(exc))
    logs.setup("api", cfg.log_level, cfg.log_format)
    raise_fd_limit()
    # The registrations' writer thread takes the GIL back after each fsync; with the default
    # 5 ms switch interval a busy event loop makes it wait that long, each time.
    sys.setswitchinterval(0.0005)
    try:
        store = Store(cfg.state_dir)
    except StoreError as exc:
        return _fail(str(exc))
    try:
        asyncio.run(_run(cfg, store, host or Host()))
    except (StartError, ConfigError, StoreError) as exc:
        return _fail(str(exc))
    except KeyboardInterrupt:  # before the signal handlers were installed
        return 130
    finally:
        store.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
