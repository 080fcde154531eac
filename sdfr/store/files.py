"""The state directory and the database file on disk: made private whatever the umask, and
the database's schema."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

from sdfr.store.records import StoreError

SCHEMA_VERSION = 3

SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS local_services (
    id TEXT PRIMARY KEY,
    seq INTEGER NOT NULL,
    body TEXT NOT NULL,
    ttl REAL,
    expires REAL,
    owner_hash TEXT,
    owner_uid INTEGER
);
CREATE TABLE IF NOT EXISTS events (
    id INTEGER PRIMARY KEY,
    kind TEXT NOT NULL,
    body TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS local_services_seq ON local_services(seq);
CREATE TABLE IF NOT EXISTS peers (
    robot_id TEXT PRIMARY KEY,
    address TEXT NOT NULL,
    location TEXT NOT NULL,
    boot_id INTEGER NOT NULL,
    version INTEGER NOT NULL,
    digest TEXT NOT NULL,
    reachable INTEGER NOT NULL,
    first_seen REAL NOT NULL,
    last_seen REAL NOT NULL,
    indicator REAL,
    rtt_ms REAL,
    pings INTEGER NOT NULL DEFAULT 0,
    services TEXT NOT NULL
);
"""


#: Bits a state directory made by hand loses: everything for others, write for the group
#: (which may be given the API socket: docs/deploy.md).
_NOT_FOR_OTHERS = 0o027


def private_dir(path: Path) -> None:
    """Create `path` (0700), or take from an existing one what others may do with it."""
    try:
        path.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError as exc:
        raise StoreError(f"state_dir: cannot create {path}: {exc.strerror}") from None
    with contextlib.suppress(OSError):  # (not ours to change: used as it is)
        mode = path.stat().st_mode & 0o7777
        if mode & _NOT_FOR_OTHERS:
            path.chmod(mode & ~_NOT_FOR_OTHERS)


def private_db(path: Path) -> None:
    """Create the database file 0600 before SQLite opens it (SQLite gives the -wal and -shm
    it creates the database's mode), and take group and others' bits from what exists."""
    try:
        os.close(os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600))
    except OSError as exc:
        raise StoreError(f"state_dir: cannot create {path}: {exc.strerror}") from None
    for name in ("", "-wal", "-shm", "-journal"):
        with contextlib.suppress(OSError):
            each = path.with_name(path.name + name)
            mode = each.stat().st_mode & 0o7777
            if mode & 0o077:
                each.chmod(mode & ~0o077)
