"""What the daemon keeps on disk is its own, whatever the umask of the shell that made the
state directory: the directory, the database and its -wal and -shm, the status file, and
the sockets, which are never seen with a wider mode, even for an instant."""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import ctypes.util
import os
import struct
from collections.abc import Iterator
from pathlib import Path

from sdfr.config.load import Config
from sdfr.daemon.apiserver import serve
from sdfr.records.model import Service
from sdfr.store import Store
from tests.support.api import aio, free_port


@contextlib.contextmanager
def umask(mask: int) -> Iterator[None]:
    old = os.umask(mask)
    try:
        yield
    finally:
        os.umask(old)


def mode(path: Path) -> int:
    return path.stat().st_mode & 0o777


def test_a_new_state_dir_and_its_database_are_private_whatever_the_umask(tmp_path: Path) -> None:
    state = tmp_path / "a" / "state"
    with umask(0):
        store = Store(state)
        try:
            store.add_service(Service("s1", "cam", "camera/rgb", None, {}))
            store.write_status({"pid": 1})
            files = sorted(p.name for p in state.iterdir())
            assert {"state.db", "state.db-wal", "state.db-shm"} <= set(files), files
            assert mode(state) == 0o700
            for name in files:
                assert mode(state / name) == 0o600, (name, oct(mode(state / name)))
        finally:
            store.close()


def test_a_state_dir_made_by_hand_is_tightened(tmp_path: Path) -> None:
    """mkdir with the shell's umask (0777 here, the worst) and a database left by a version
    that did not care: no one but the daemon's user (and the directory's group, which may
    be given the API socket) can read them after the next start."""
    state = tmp_path / "state"
    with umask(0):
        state.mkdir(mode=0o777)
        Store(state).close()
        for name in ("state.db", "state.db-wal", "state.db-shm"):
            if (state / name).exists():
                (state / name).chmod(0o666)
        (state / "state.db").chmod(0o666)
        Store(state).close()
    assert mode(state) & 0o027 == 0, oct(mode(state))  # no write for the group, nothing more
    for path in state.glob("state.db*"):
        assert mode(path) == 0o600, (path.name, oct(mode(path)))


# -- the sockets: created private ---------------------------------------------------------------

IN_CREATE, IN_MOVED_TO, IN_ATTRIB = 0x100, 0x80, 0x4
_EVENT = struct.Struct("iIII")


class Inotify:
    """What happens to the names in one directory (IN_CREATE, IN_MOVED_TO, IN_ATTRIB)."""

    def __init__(self, directory: Path) -> None:
        libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
        self.fd = libc.inotify_init1(os.O_NONBLOCK)
        assert self.fd >= 0, os.strerror(ctypes.get_errno())
        mask = IN_CREATE | IN_MOVED_TO | IN_ATTRIB
        assert libc.inotify_add_watch(self.fd, os.fsencode(directory), mask) >= 0

    def events(self) -> list[tuple[str, int]]:
        """(name, mask) of each event so far, in order."""
        out = []
        with contextlib.suppress(BlockingIOError):
            while data := os.read(self.fd, 65536):
                pos = 0
                while pos < len(data):
                    _, mask, _, size = _EVENT.unpack_from(data, pos)
                    raw = data[pos + _EVENT.size : pos + _EVENT.size + size]
                    out.append((raw.rstrip(b"\0").decode(), mask))
                    pos += _EVENT.size + size
        return out

    def close(self) -> None:
        os.close(self.fd)


@aio
async def test_the_sockets_appear_with_their_mode_already_set(tmp_path: Path) -> None:
    """api.sock and status.sock come into the state directory by a rename of a socket that
    was bound and given its mode in a private directory: never created in place, so never
    there with the mode the umask gives (here 0777), even for an instant."""
    state = tmp_path / "s"
    with umask(0):
        store = Store(state)
    cfg = Config(state_dir=state, robot_id="r1", iface="lo", api=f"127.0.0.1:{free_port()}")
    watch = Inotify(state)
    stop = asyncio.Event()
    try:
        with umask(0):
            task = asyncio.get_running_loop().create_task(serve(cfg, store, stop))
            for _ in range(200):
                await asyncio.sleep(0.02)
                if (state / "api.sock").exists() and (state / "status.sock").exists():
                    break
        assert mode(state / "api.sock") == 0o660
        assert mode(state / "status.sock") == 0o660
        seen = watch.events()
        for name in ("api.sock", "status.sock"):
            how = [m for n, m in seen if n == name]
            assert how == [IN_MOVED_TO], (name, seen)
        stop.set()
        await task
    finally:
        stop.set()
        watch.close()
        store.close()
