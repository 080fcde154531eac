"""The Store: one connection to the state database (the package's docstring says what it holds
and who writes what)."""

from __future__ import annotations

import contextlib
import json
import os
import sqlite3
import time
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

from sdfr.records import events as event_log
from sdfr.records.events import Event
from sdfr.records.model import PeerRecord, Service, json_array
from sdfr.store.files import SCHEMA, SCHEMA_VERSION, private_db, private_dir
from sdfr.store.records import (
    DAEMON,
    Add,
    Caller,
    Expire,
    Lease,
    NotOwner,
    Op,
    Remove,
    Renew,
    StoredEvent,
    StoreError,
    write_error,
)
from sdfr.wire import MAX_BOOT_ID

#: Events the log keeps (each is at most a few KiB: see sdfr.records.events.MAX_SERVICES_JSON).
EVENT_LOG_MAX = 4096
#: Boot ids count seconds from 2020-01-01 UTC (BOOTID.UPNP.ORG holds 31 bits: until 2088).
BOOT_EPOCH = 1577836800


def _service_from_row(body: str) -> Service:
    obj = json.loads(body)
    return Service.from_json(obj)


def _dumps(obj: Any) -> str:
    return json.dumps(obj, separators=(",", ":"), ensure_ascii=False)


#: PRAGMA synchronous of an ordinary commit, and of a durable one (fsynced before visible).
_NORMAL, _FULL = 1, 2


class Store:
    """One connection to the state database; each process opens its own."""

    def __init__(self, state_dir: Path) -> None:
        private_dir(state_dir)
        if not os.access(state_dir, os.W_OK):
            raise StoreError(f"state_dir: {state_dir} is not writable")
        self.path = state_dir / "state.db"
        private_db(self.path)
        self._synchronous = _NORMAL
        try:
            self._db = sqlite3.connect(
                self.path, timeout=10.0, isolation_level=None, check_same_thread=False
            )
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.executescript(SCHEMA)
            self._migrate()
        except sqlite3.DatabaseError as exc:
            raise StoreError(
                f"state_dir: {self.path} is not a usable SDfR database: {exc}"
            ) from None
        self.status_path = state_dir / "discovery-status.json"
        self.wal_path = self.path.with_name(self.path.name + "-wal")
        self._dir_synced = False
        # Parsed service sets by their stored JSON text: a reload after an indicator update
        # parses nothing again. (Not by version: a peer is saved with no services while its
        # announced set is still being fetched, then again with them, under one version.)
        self._parsed: dict[str, tuple[Service, ...]] = {}
        # The local services by their stored JSON text: a reload after one publish parses
        # one service, not the whole set (both layers reload it after every change).
        self._local_parsed: dict[str, Service] = {}

    def close(self) -> None:
        self._db.close()

    def _migrate(self) -> None:
        """Bring a state directory of an earlier version up to this one (nothing is lost)."""
        columns = {r[1] for r in self._db.execute("PRAGMA table_info(local_services)")}
        added = (("ttl", "REAL"), ("expires", "REAL"), ("owner_hash", "TEXT"), ("owner_uid", "INT"))
        for name, kind in added:
            if name not in columns:  # schema 1 had no lease, 2 no owner
                self._db.execute(f"ALTER TABLE local_services ADD COLUMN {name} {kind}")
        self._db.execute(
            "INSERT INTO meta(key, value) VALUES ('schema', ?) "
            "ON CONFLICT(key) DO UPDATE SET value = excluded.value "
            "WHERE CAST(value AS INTEGER) < CAST(excluded.value AS INTEGER)",
            (str(SCHEMA_VERSION),),
        )

    # -- meta ------------------------------------------------------------------------------

    def get_meta(self, key: str) -> str | None:
        row = self._db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return None if row is None else str(row[0])

    def set_meta(self, key: str, value: str) -> None:
        self._db.execute(
            "INSERT INTO meta(key, value) VALUES (?, ?) "
            "ON CONFLICT(key) DO UPDATE SET value = excluded.value",
            (key, value),
        )

    def next_boot_id(self, now: float) -> int:
        """A boot id for a start at Unix time `now`: the seconds since 2020, or one more than
        any this state directory handed out before if that is larger.

        So it is new on every start even when the state directory is lost (a re-imaged
        robot, a fresh container), as long as the clock is right; peers tell a robot whose
        state and clock were both lost by a round trip, not by its boot id.
        """
        with self._tx():
            last = int(self.get_meta("boot_id") or "0")
            boot = max(last + 1, int(now) - BOOT_EPOCH)
            if boot > MAX_BOOT_ID:  # a clock past 2088, or 2**31 restarts: start over
                boot = 1
            self.set_meta("boot_id", str(boot))
        return boot

    def data_version(self) -> int:
        """Changes whenever another connection commits (cheap cache validation)."""
        return int(self._db.execute("PRAGMA data_version").fetchone()[0])

    # -- local registrations (owner: API layer) --------------------------------------------

    def local_version(self) -> int:
        return int(self.get_meta("local_version") or "0")

    def local_state(self) -> tuple[int, list[Service]]:
        """The version and the services it names, read in one snapshot."""
        with self._tx(immediate=False):
            version = self.local_version()
            rows = self._db.execute("SELECT body FROM local_services ORDER BY seq").fetchall()
        known, parsed = self._local_parsed, {}
        for (body,) in rows:
            service = known.get(body)
            parsed[body] = service if service is not None else _service_from_row(body)
        self._local_parsed = parsed
        return version, [parsed[body] for (body,) in rows]

    def sync(self) -> None:
        """Make what was committed so far durable: fsync the write-ahead log (and, the first
        time, the directory holding it). A failure raises StateWriteError."""
        with self._writing():
            fd = os.open(self.wal_path, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
            self._sync_dir()

    def _sync_dir(self) -> None:
        """fsync the state directory once (the names of the database and its log)."""
        if not self._dir_synced:
            dfd = os.open(self.path.parent, os.O_RDONLY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)
            self._dir_synced = True

    def get_service(self, service_id: str) -> Service | None:
        row = self._db.execute(
            "SELECT body FROM local_services WHERE id = ?", (service_id,)
        ).fetchone()
        return None if row is None else _service_from_row(row[0])

    def apply(
        self, ops: Sequence[Op], now: float | None = None, *, durable: bool = False
    ) -> list[int | StoreError | None]:
        """Several registration changes in one transaction, each with its event: per operation
        the new local version (Renew: 0), None (removing, renewing or expiring what is not
        there, or was renewed since) or the error (adding an id that exists: StoreError; a
        change by someone who does not own the registration: NotOwner). A failed write raises
        StateWriteError for all, and nothing of it is committed.

        `durable`: the commit is fsynced before it is visible (one fsync for all), so that
        what is answered afterwards is on disk; if the fsync fails, nothing was committed.
        `now`: Unix time."""
        now = time.time() if now is None else now
        out: list[int | StoreError | None] = []
        events: list[Event] = []
        with self._writing():
            level = _FULL if durable else _NORMAL
            if level != self._synchronous:
                self._db.execute(f"PRAGMA synchronous={level}")
                self._synchronous = level
            if durable:
                self._sync_dir()
        with self._writing(), self._tx():
            for op in ops:
                if isinstance(op, Add):
                    out.append(self._insert(op.service, op.ttl, op.owner, now, events))
                elif isinstance(op, Remove):
                    out.append(self._delete(op.service_id, None, events, op.caller))
                elif isinstance(op, Expire):
                    out.append(self._delete(op.service_id, op.expires, events))
                else:
                    out.append(self._renew(op, now, events))
            self._append(events, now)
        return out

    def _insert(
        self, service: Service, ttl: float | None, owner: Caller, now: float, events: list[Event]
    ) -> int | StoreError:
        seq = self._db.execute("SELECT COALESCE(MAX(seq), 0) + 1 FROM local_services").fetchone()[0]
        expires = None if ttl is None else now + ttl
        try:
            self._db.execute(
                "INSERT INTO local_services(id, seq, body, ttl, expires, owner_hash, owner_uid) "
                "VALUES (?, ?, ?, ?, ?, ?, ?)",
                (
                    service.id,
                    seq,
                    service.json_text().decode(),
                    ttl,
                    expires,
                    owner.token_hash,
                    owner.uid,
                ),
            )
        except sqlite3.IntegrityError:
            return StoreError(f"service id {service.id!r} exists already")
        events.append(event_log.published(service, ttl, expires))
        return self._bump_version()

    def _delete(
        self,
        service_id: str,
        expires: float | None,
        events: list[Event],
        caller: Caller = DAEMON,
    ) -> int | NotOwner | None:
        row = self._db.execute(
            "SELECT body, expires, owner_hash, owner_uid FROM local_services WHERE id = ?",
            (service_id,),
        ).fetchone()
        if row is None or (expires is not None and row[1] != expires):
            return None  # not there; or an expiry of a lease renewed since
        if not caller.owns(row[2], row[3]):
            return NotOwner(f"service {service_id!r} belongs to another program")
        self._db.execute("DELETE FROM local_services WHERE id = ?", (service_id,))
        if expires is None:
            events.append(event_log.unpublished(service_id))
        else:
            events.append(event_log.expired(_service_from_row(row[0])))
        return self._bump_version()

    def _renew(self, op: Renew, now: float, events: list[Event]) -> int | NotOwner | None:
        row = self._db.execute(
            "SELECT body, ttl, owner_hash, owner_uid FROM local_services WHERE id = ?",
            (op.service_id,),
        ).fetchone()
        if row is None:
            return None
        if not op.caller.owns(row[2], row[3]):
            return NotOwner(f"service {op.service_id!r} belongs to another program")
        ttl = op.ttl if op.set_ttl or op.ttl is not None else row[1]
        if ttl is None and not op.set_ttl:
            return None  # no lease to renew
        expires = None if ttl is None else now + ttl
        self._db.execute(
            "UPDATE local_services SET ttl = ?, expires = ? WHERE id = ?",
            (ttl, expires, op.service_id),
        )
        if op.set_ttl and ttl != row[1]:  # a publish again under another lease: say so
            events.append(event_log.published(_service_from_row(row[0]), ttl, expires))
        return 0

    def lease(self, service_id: str) -> Lease | None:
        """The lease of a registration, None if it has none (or does not exist)."""
        row = self._db.execute(
            "SELECT ttl, expires FROM local_services WHERE id = ? AND expires IS NOT NULL",
            (service_id,),
        ).fetchone()
        return None if row is None else Lease(service_id, float(row[0]), float(row[1]))

    def leases(self) -> list[Lease]:
        """Every lease, soonest to end first."""
        rows = self._db.execute(
            "SELECT id, ttl, expires FROM local_services WHERE expires IS NOT NULL ORDER BY expires"
        ).fetchall()
        return [Lease(r[0], float(r[1]), float(r[2])) for r in rows]

    def expire_overdue(self, now: float) -> list[str]:
        """Withdraw every registration whose lease ended before `now` (Unix time), e.g. while
        the daemon was down; the ids withdrawn."""
        overdue = [lease for lease in self.leases() if lease.expires <= now]
        results = self.apply([Expire(x.service_id, x.expires) for x in overdue], now)
        return [x.service_id for x, r in zip(overdue, results, strict=True) if r is not None]

    def add_service(self, service: Service, ttl: float | None = None) -> int:
        """Store a registration; returns the new local version."""
        result = self.apply([Add(service, ttl)])[0]
        if isinstance(result, StoreError):
            raise result
        assert result is not None
        return result

    def remove_service(self, service_id: str) -> int | None:
        """Remove a registration; returns the new local version, None if there was none."""
        result = self.apply([Remove(service_id)])[0]
        assert not isinstance(result, StoreError)
        return result

    def _bump_version(self) -> int:
        version = self.local_version() + 1
        self.set_meta("local_version", str(version))
        return version

    # -- history map (owner: discovery layer) ----------------------------------------------

    def save_peers(
        self, records: Iterable[PeerRecord], events: Sequence[Event] = (), now: float | None = None
    ) -> None:
        """Save history map records, and the events they make, in one transaction."""
        self.save_history((), records, events, now)

    def save_history(
        self,
        removed: Iterable[str],
        records: Iterable[PeerRecord],
        events: Sequence[Event] = (),
        now: float | None = None,
    ) -> None:
        """Forget the robots `removed`, save `records`, append `events`: one transaction."""
        rows = [
            (
                r.robot_id,
                r.address,
                r.location,
                r.boot_id,
                r.version,
                r.digest,
                int(r.reachable),
                r.first_seen,
                r.last_seen,
                r.indicator,
                r.rtt_ms,
                r.pings,
                json_array(r.services).decode(),
            )
            for r in records
        ]
        ids = [(r,) for r in removed]
        if not rows and not ids and not events:
            return
        with self._writing(), self._tx():
            self._db.executemany("DELETE FROM peers WHERE robot_id = ?", ids)
            self._db.executemany(
                "INSERT OR REPLACE INTO peers(robot_id, address, location, boot_id, version, "
                "digest, reachable, first_seen, last_seen, indicator, rtt_ms, pings, services) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                rows,
            )
            self._append(events, time.time() if now is None else now)

    def load_peers(self) -> list[PeerRecord]:
        rows = self._db.execute(
            "SELECT robot_id, address, location, boot_id, version, digest, reachable, first_seen, "
            "last_seen, indicator, rtt_ms, pings, services FROM peers ORDER BY robot_id"
        ).fetchall()
        parsed: dict[str, tuple[Service, ...]] = {}
        out = []
        for r in rows:
            text: str = r[12]
            services = self._parsed.get(text)
            if services is None:
                services = tuple(Service.from_json(s) for s in json.loads(text))
            parsed[text] = services
            out.append(
                PeerRecord(
                    robot_id=r[0],
                    address=r[1],
                    location=r[2],
                    boot_id=r[3],
                    version=r[4],
                    digest=r[5],
                    reachable=bool(r[6]),
                    first_seen=r[7],
                    last_seen=r[8],
                    indicator=r[9],
                    rtt_ms=r[10],
                    pings=r[11],
                    services=services,
                )
            )
        self._parsed = parsed
        return out

    def delete_peers(self, robot_ids: Iterable[str], events: Sequence[Event] = ()) -> None:
        """Forget robots (the history map was full)."""
        self.save_history(robot_ids, (), events)

    def mark_all_unreachable(self, events: Sequence[Event] = ()) -> None:
        """At discovery start nothing is known to be reachable yet (`events` tell it)."""
        with self._writing(), self._tx():
            self._db.execute("UPDATE peers SET reachable = 0 WHERE reachable != 0")
            self._append(events, time.time())

    # -- the event log (both layers append; the API layer reads) ---------------------------

    def _append(self, events: Sequence[Event], now: float) -> None:
        """Append to the log inside the caller's transaction; drop what is past EVENT_LOG_MAX."""
        if not events:
            return
        last = self.last_event_id()
        rows = []
        for event in events:
            last = max(last + 1, int(now * 1_000_000))
            rows.append((last, event.kind, event.body(last, now)))
        self._db.executemany("INSERT INTO events(id, kind, body) VALUES (?, ?, ?)", rows)
        edge = self._db.execute(
            "SELECT id FROM events ORDER BY id DESC LIMIT 1 OFFSET ?", (EVENT_LOG_MAX,)
        ).fetchone()
        if edge is not None:
            self._db.execute("DELETE FROM events WHERE id <= ?", (edge[0],))
            self.set_meta("events_pruned", str(edge[0]))

    def last_event_id(self) -> int:
        """The id of the newest event (0 when there is none)."""
        row = self._db.execute("SELECT MAX(id) FROM events").fetchone()
        return 0 if row[0] is None else int(row[0])

    def events_pruned(self) -> int:
        """The largest id dropped from the log (0: nothing was ever dropped)."""
        return int(self.get_meta("events_pruned") or "0")

    def events_after(self, after: int, limit: int = 256) -> list[StoredEvent]:
        """Events with an id above `after`, oldest first, at most `limit`."""
        rows = self._db.execute(
            "SELECT id, kind, body FROM events WHERE id > ? ORDER BY id LIMIT ?", (after, limit)
        ).fetchall()
        return [StoredEvent(int(r[0]), str(r[1]), str(r[2])) for r in rows]

    # -- discovery status (owner: discovery layer) -----------------------------------------

    def write_status(self, status: dict[str, Any]) -> None:
        """Heartbeat, pid, counters and the local view, read by the API for /health, /metrics.

        A file replaced atomically, not a row: a heartbeat every second must not change
        the database's data_version, which the API uses to know the history map changed.
        """
        status = {**status, "heartbeat": time.time()}
        tmp = self.status_path.with_suffix(".tmp")
        with self._writing():
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o600)
            try:
                os.fchmod(fd, 0o600)  # (one left by a crash may have had another mode)
                os.write(fd, _dumps(status).encode())
            finally:
                os.close(fd)
            tmp.replace(self.status_path)

    def read_status(self) -> dict[str, object]:
        try:
            obj = json.loads(self.status_path.read_text())
        except (OSError, ValueError):
            return {}
        return obj if isinstance(obj, dict) else {}

    # -- helpers ---------------------------------------------------------------------------

    @contextlib.contextmanager
    def _writing(self) -> Iterator[None]:
        """Failed writes raise StateWriteError, saying whether the disk is full or read-only."""
        try:
            yield
        except (sqlite3.DatabaseError, OSError) as exc:
            raise write_error(self.path.parent, exc) from None

    def _commit(self) -> None:
        """COMMIT a write transaction (with synchronous=FULL, SQLite fsyncs the log first, and
        a failed fsync fails the commit: "disk I/O error")."""
        self._db.execute("COMMIT")

    class _Tx:
        def __init__(self, store: Store, immediate: bool) -> None:
            self._store = store
            self._db = store._db
            self._immediate = immediate

        def __enter__(self) -> None:
            self._db.execute("BEGIN IMMEDIATE" if self._immediate else "BEGIN")

        def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
            if exc_type is None:
                try:
                    if self._immediate:
                        self._store._commit()
                    else:
                        self._db.execute("COMMIT")
                    return
                except sqlite3.DatabaseError:
                    # (A full disk or a failed fsync can fail the commit itself: end the
                    # transaction, or every later one on this connection fails too.)
                    with contextlib.suppress(sqlite3.DatabaseError):
                        self._db.execute("ROLLBACK")
                    raise
            with contextlib.suppress(sqlite3.DatabaseError):
                self._db.execute("ROLLBACK")

    def _tx(self, immediate: bool = True) -> Store._Tx:
        return Store._Tx(self, immediate)
