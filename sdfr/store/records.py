"""The store's records and errors: the changes of local registrations (`Add`, `Remove`,
`Renew`, `Expire`) and who asks for them (`Caller`), a lease, a stored event, and why a write
of the state directory failed."""

from __future__ import annotations

import errno
import hashlib
import hmac
from dataclasses import dataclass
from pathlib import Path

from sdfr.errors import SdfrError
from sdfr.records.model import Service


class StoreError(SdfrError):
    """The state directory cannot be used."""


class NotOwner(StoreError):
    """A change of a registration asked by someone other than its owner."""


class StateWriteError(StoreError):
    """A write to the state directory failed: `reason` is full, read-only or error."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def write_reason(code: int | None, text: str = "") -> str:
    """Why a write failed, from its errno or (SQLite says it in words) its message: full,
    read-only or error."""
    text = text.lower()
    if code in (errno.ENOSPC, errno.EDQUOT) or "full" in text:
        return "full"
    if code == errno.EROFS or "readonly" in text or "read-only" in text:
        return "read-only"
    return "error"


def write_error(where: Path, exc: BaseException) -> StateWriteError:
    """A write failure, classified: a full disk, a read-only one, or something else."""
    reason = write_reason(getattr(exc, "errno", None), str(exc))
    if reason == "full":
        return StateWriteError(reason, f"the state directory {where} is full ({exc})")
    if reason == "read-only":
        return StateWriteError(reason, f"the state directory {where} is read-only ({exc})")
    return StateWriteError(reason, f"cannot write the state directory {where}: {exc}")


def hash_token(token: str) -> str:
    """What the store keeps of an owner token: its SHA-256, in hex."""
    return hashlib.sha256(token.encode()).hexdigest()


@dataclass(frozen=True, slots=True)
class Caller:
    """Who publishes, or asks to change a registration: the hash of the owner token it
    presented (None: none) and, on the unix socket, its uid (None: not known, e.g. TCP)."""

    token_hash: str | None = None
    uid: int | None = None

    def owns(self, token_hash: str | None, uid: int | None) -> bool:
        """Whether it may change a registration whose owner is (`token_hash`, `uid`): its
        token's, its user's (root's: any); one stored before registrations had owners
        (both None) is anyone's."""
        if token_hash is None and uid is None:
            return True
        if self.uid is not None and (self.uid == 0 or self.uid == uid):
            return True
        return (
            self.token_hash is not None
            and token_hash is not None
            and hmac.compare_digest(self.token_hash, token_hash)
        )


#: The daemon itself (an expiry, a test): may change anything.
DAEMON = Caller(uid=0)


@dataclass(frozen=True, slots=True)
class Add:
    """Register a service; with a ttl (seconds), as a lease that ends at `now + ttl`; owned
    by `owner` (its token's hash, its uid; neither: anyone's)."""

    service: Service
    ttl: float | None = None
    owner: Caller = Caller()


@dataclass(frozen=True, slots=True)
class Remove:
    """Unpublish a service (NotOwner unless `caller` owns it)."""

    service_id: str
    caller: Caller = DAEMON


@dataclass(frozen=True, slots=True)
class Renew:
    """Extend a lease to `now + ttl` (its own ttl when None); with `set_ttl`, make `ttl` the
    lease's ttl (None: no lease any more): a publish again. NotOwner unless `caller` owns it."""

    service_id: str
    ttl: float | None = None
    set_ttl: bool = False
    caller: Caller = DAEMON


@dataclass(frozen=True, slots=True)
class Expire:
    """Withdraw a service whose lease ran out, unless it was renewed since: `expires` is
    the end its owner last set."""

    service_id: str
    expires: float


#: A write of local registrations.
Op = Add | Remove | Renew | Expire


@dataclass(frozen=True, slots=True)
class Lease:
    """A registration's lease: its ttl and when it ends (Unix time)."""

    service_id: str
    ttl: float
    expires: float


@dataclass(frozen=True, slots=True)
class StoredEvent:
    """A row of the event log: its id, kind and the JSON `GET /events` sends."""

    id: int
    kind: str
    body: str
