"""Durable state shared by the two layers: SQLite in WAL mode.

Owners: the API layer writes local registrations (`local_services`, the local
version); the discovery layer writes the history map (`peers`) and its status.
Each reads what the other writes. WAL lets readers proceed while a writer
commits. Commits run with synchronous=NORMAL (they survive a crash of the process),
but a durable one (`apply(..., durable=True)`: what the API answers 2xx for) runs
with synchronous=FULL: SQLite fsyncs the write-ahead log before the commit becomes
visible, so an acknowledged registration is on disk and survives a power cut, and one
whose fsync failed was never seen by any reader (nor announced). The history map,
rebuilt from the air in seconds, is not synced.

Owners of registrations: each row keeps the SHA-256 of its owner token and, when it was
published over the unix socket, the publishing user's uid; an unpublish or renewal by
anyone else is refused (`NotOwner`), root's on the unix socket excepted. The token itself
is never stored.

Files: the state directory is made private (0700 when created; an existing one loses its
bits for others and the group's write), and the database and its -wal and -shm are 0600,
whatever the umask.

Leases: a registration may carry a ttl; its row keeps the ttl and the Unix time it expires
(`expires`), so a lease outlives a restart of the daemon and one that ran out while the daemon
was down is withdrawn when it starts (`expire_overdue`).

The event log (`events`): both layers append the changes they make, in the transaction that
makes them, for `GET /events`. An event's id is one more than the last one's, or the time in
microseconds when that is larger: ids grow across restarts, and also past events a power cut
lost (which were never fsynced) as long as the clock goes forward. The log keeps the last
EVENT_LOG_MAX events; `meta.events_pruned` is the largest id dropped, so a reader asking for
events after an older id learns that some are gone.
"""

from sdfr.store.db import BOOT_EPOCH, EVENT_LOG_MAX, Store
from sdfr.store.files import SCHEMA_VERSION
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
    StateWriteError,
    StoredEvent,
    StoreError,
    hash_token,
    write_error,
    write_reason,
)

__all__ = [
    "BOOT_EPOCH",
    "DAEMON",
    "EVENT_LOG_MAX",
    "SCHEMA_VERSION",
    "Add",
    "Caller",
    "Expire",
    "Lease",
    "NotOwner",
    "Op",
    "Remove",
    "Renew",
    "StateWriteError",
    "Store",
    "StoreError",
    "StoredEvent",
    "hash_token",
    "write_error",
    "write_reason",
]
