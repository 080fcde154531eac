"""A synchronous Python client of sdfrd's REST API, on http.client.

    with Client() as sdfr:                      # 127.0.0.1:8700
        sid = sdfr.publish("front camera", "camera/rgb", attributes={"fps": 30})
        for robot in sdfr.search("camera/rgb", fps=30):
            ...
        with sdfr.lease("arm", "actuator/arm", ttl=10):   # withdrawn if this program dies
            ...
        for change in sdfr.watch(["robot"]):     # live changes (GET /events)
            ...

One keep-alive connection per client (TCP, or the daemon's unix socket
STATE_DIR/api.sock); not safe to share between threads. A client is one program to sdfrd:
what it publishes belongs to its owner token (`owner_token`, made for it unless given;
keep it to unpublish after a restart of the program), sent with every call.
`sdfr.aio.AsyncClient` has the same methods for asyncio: both are `sdfr.client.core.Api`
(every call written once, in `sdfr.client.calls`), carried over their transport.
"""

from __future__ import annotations

import http.client
import json
import os
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, TypeVar

from sdfr.client import calls
from sdfr.client.calls import (
    RETRY_DELAYS,
    STREAM_IDLE,
    Call,
    Change,
    JsonObject,
    neighbors_path,
    new_owner_token,
    new_service_id,
    search_path,
    service_path,
    split_api,
)
from sdfr.client.core import Api, Lease, LeaseKeeping, Plan, Stepper, SyncTransport, Watch, attempts
from sdfr.errors import ApiError

T = TypeVar("T")

__all__ = [
    "RETRY_DELAYS",
    "Change",
    "Client",
    "JsonObject",
    "KeptLease",
    "UnixHTTPConnection",
    "neighbors_path",
    "new_service_id",
    "owner_token_path",
    "search_path",
    "service_path",
    "split_api",
    "user_owner_token",
]

# What a server closing an idle keep-alive connection looks like; worth one fresh attempt.
_DROPPED = (
    http.client.RemoteDisconnected,
    ConnectionResetError,
    ConnectionAbortedError,
    BrokenPipeError,
)


class UnixHTTPConnection(http.client.HTTPConnection):
    """HTTP over a unix stream socket."""

    def __init__(self, path: str, timeout: float | None = None) -> None:
        super().__init__("localhost", timeout=timeout)
        self.path = path

    def connect(self) -> None:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            sock.settimeout(self.timeout)
            sock.connect(self.path)
        except OSError:
            sock.close()
            raise
        self.sock = sock


def owner_token_path() -> Path:
    """Where this user's owner token is kept: $XDG_STATE_HOME/sdfr-cli/owner-token."""
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "sdfr-cli" / "owner-token"


def user_owner_token() -> str | None:
    """This user's owner token, made (0600) on first use: what `sdfr publish` (or the ROS
    node) published, a later run can unpublish or publish again. None when it cannot be kept
    (each run is then a program of its own; the unix socket still goes by user)."""
    path = owner_token_path()
    for _ in range(2):
        try:
            token = path.read_text().strip()
            return token or None
        except FileNotFoundError:
            pass
        except (OSError, UnicodeDecodeError):
            return None
        try:
            path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:
            continue  # another run made it meanwhile: read it
        except OSError:
            return None
        token = new_owner_token()
        with os.fdopen(fd, "w") as f:
            f.write(token + "\n")
        return token
    return None


def _reason(exc: BaseException) -> str:
    if isinstance(exc, TimeoutError):
        return "timed out"
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc) or type(exc).__name__


class Client(Api, SyncTransport["KeptLease"]):
    """sdfrd's REST API; every method raises ApiError (status 0: the daemon was not reached).
    The methods are `sdfr.client.core.Api`'s; this carries them over http.client."""

    _conn: http.client.HTTPConnection | None = None

    # -- plumbing ----------------------------------------------------------------------------

    def close(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _twin(self) -> Client:
        """Another client of the same daemon (for a thread of its own)."""
        return Client(
            self.api,
            unix_socket=self._unix,
            timeout=self.timeout,
            retry_delays=(),
            owner_token=self.owner_token,
            api_token=self.api_token,
        )

    def _connection(self, timeout: float | None = None) -> http.client.HTTPConnection:
        timeout = self.timeout if timeout is None else timeout
        if self._unix is not None:
            return UnixHTTPConnection(self._unix, timeout=timeout)
        return http.client.HTTPConnection(self._host, self._port, timeout=timeout)

    def _exchange(self, method: str, path: str, body: bytes | None) -> tuple[int, str, bytes]:
        headers = self._headers()
        if body is not None:
            headers["Content-Type"] = "application/json"
        while True:
            fresh = self._conn is None
            conn = self._conn = self._conn or self._connection()
            try:
                conn.request(method, path, body=body, headers=headers)
                resp = conn.getresponse()
                data = resp.read()
            except _DROPPED as exc:
                self.close()
                if not fresh:
                    continue  # the server closed the idle connection: once more on a new one
                raise self._unreachable(_reason(exc)) from None
            except (OSError, http.client.HTTPException) as exc:
                self.close()
                raise self._unreachable(_reason(exc)) from None
            if resp.will_close:
                self.close()
            return resp.status, resp.getheader("Content-Type", ""), data

    def _send(self, call: Call[T]) -> T:
        payload = None if call.body is None else json.dumps(call.body).encode()
        status, ctype, data = self._exchange(call.method, call.path, payload)
        return calls.answer(call, status, ctype, data)

    def _run(self, plan: Plan[T]) -> T:
        run = Stepper(plan)
        while run.effect is not None:
            if not isinstance(run.effect, Call):
                time.sleep(run.effect)
                run.give(None)
                continue
            try:
                value = self._send(run.effect)
            except ApiError as exc:
                run.fail(exc)
                continue
            run.give(value)
        return run.result

    def call(self, call: Call[T]) -> T:
        """Carry out one call of `sdfr.client.calls`; sent again after RETRY_DELAYS when it may be
        and sdfrd could not be reached."""
        return self._run(attempts(call, self.retry_delays))

    def _carry(self, made: Any) -> Any:
        if isinstance(made, Call):
            return self.call(made)
        if isinstance(made, Lease):
            self.call(made.publish)
            return KeptLease(self._twin(), made)
        return self._follow(made)

    def _follow(self, watch: Watch) -> Iterator[Change]:
        while True:
            conn = self._connection(STREAM_IDLE)
            try:
                conn.request("GET", watch.path, headers=watch.headers(self._headers()))
                resp = conn.getresponse()
                if resp.status != 200:
                    watch.refused(resp.status, resp.getheader("Content-Type", ""), resp.read())
                watch.opened()
                while raw := resp.readline():
                    if (change := watch.line(raw)) is not None:
                        yield change
            except (OSError, http.client.HTTPException) as exc:
                watch.broken(self._unreachable(_reason(exc)))
            finally:
                conn.close()
            pause = watch.pause()
            if pause is None:
                return
            time.sleep(pause)


class KeptLease(LeaseKeeping):
    """A registration with a lease (`Client.lease`), renewed from a thread each
    RENEW_EVERY of its ttl, and published again (same id) if it ran out meanwhile (sdfrd
    was down longer than the ttl). `close()` stops renewing and unpublishes it."""

    def __init__(self, client: Client, lease: Lease) -> None:
        super().__init__(lease)
        self._client = client
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._keep, name=f"sdfr-lease-{self.id}")
        self._thread.daemon = True
        self._thread.start()

    def _keep(self) -> None:
        while not self._stop.wait(self.period):
            try:
                self._client._run(self.renewal())
            except ApiError as exc:
                self.renewed(exc)
            else:
                self.renewed()

    def close(self) -> None:
        """Stop renewing and unpublish (quietly if it is gone already)."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join()
        try:
            self._client._run(self.withdrawal())
        finally:
            self._client.close()

    def __enter__(self) -> KeptLease:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
