"""A synchronous Python client of sdfrd's REST API (standard library only).

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
`sdfr.aio.AsyncClient` has the same calls for asyncio; both are made of the call definitions
in `sdfr.calls`.
"""

from __future__ import annotations

import base64
import http.client
import json
import os
import socket
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, TypeVar

from sdfr import calls
from sdfr.calls import (
    RENEW_EVERY,
    RETRY_DELAYS,
    STREAM_HEADERS,
    STREAM_IDLE,
    Call,
    Change,
    EventsPage,
    Health,
    JsonObject,
    Published,
    Renewed,
    SseParser,
    neighbors_path,
    new_owner_token,
    new_service_id,
    request_headers,
    search_path,
    service_body,
    service_path,
    split_api,
)
from sdfr.config import DEFAULT_API
from sdfr.errors import ApiError
from sdfr.model import AttrValue

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
    "service_body",
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


class Client:
    """sdfrd's REST API; every method raises ApiError (status 0: the daemon was not reached)."""

    def __init__(
        self,
        api: str = DEFAULT_API,
        *,
        unix_socket: str | Path | None = None,
        timeout: float = 5.0,
        retry_delays: Sequence[float] = RETRY_DELAYS,
        owner_token: str | None = None,
        api_token: str | None = None,
    ) -> None:
        self.api = api
        self.timeout = timeout
        #: Pauses before sending a publish again when sdfrd could not be reached.
        self.retry_delays = tuple(retry_delays)
        #: What this client publishes belongs to this token (sent with every call).
        self.owner_token = owner_token or new_owner_token()
        #: The token of sdfrd's api_token_file, for an API on another machine.
        self.api_token = api_token
        self._conn: http.client.HTTPConnection | None = None
        if unix_socket is not None:
            self._unix: str | None = str(unix_socket)
            self.where = self._unix
            self._host, self._port = "localhost", 0
        else:
            self._unix = None
            self._host, self._port = split_api(api)
            self.where = f"{self._host}:{self._port}"

    # -- plumbing ----------------------------------------------------------------------------

    def close(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def __enter__(self) -> Client:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
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

    def _unreachable(self, exc: BaseException) -> ApiError:
        return calls.unreachable(self.where, _reason(exc), self._unix is not None)

    def _exchange(self, method: str, path: str, body: bytes | None) -> tuple[int, str, bytes]:
        headers = request_headers(self.owner_token, self.api_token)
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
                raise self._unreachable(exc) from None
            except (OSError, http.client.HTTPException) as exc:
                self.close()
                raise self._unreachable(exc) from None
            if resp.will_close:
                self.close()
            return resp.status, resp.getheader("Content-Type", ""), data

    def call(self, call: Call[T]) -> T:
        """Carry out one call of `sdfr.calls`; sent again after RETRY_DELAYS when it may be
        and sdfrd could not be reached."""
        payload = None if call.body is None else json.dumps(call.body).encode()
        delays = self.retry_delays if call.retry_unreachable else ()
        for delay in (*delays, None):
            try:
                status, ctype, data = self._exchange(call.method, call.path, payload)
            except ApiError:
                if delay is None:
                    raise
                time.sleep(delay)
                continue
            return calls.answer(call, status, ctype, data)
        raise AssertionError("unreachable")

    def request(
        self,
        method: str,
        path: str,
        body: Any = None,
        *,
        accept: tuple[int, ...] = (),
    ) -> Any:
        """One call of any path: the decoded JSON answer (None when empty); errors raise
        ApiError. `accept` lists error statuses whose body is returned instead."""
        return self.call(Call(method, path, lambda answer: answer, body, accept))

    # -- the API -----------------------------------------------------------------------------

    def publish(
        self,
        name: str,
        type: str,
        url: str | None = None,
        attributes: Mapping[str, AttrValue] | None = None,
        *,
        service_id: str | None = None,
        ttl: float | None = None,
    ) -> str:
        """Publish a service of this robot; returns its id (see `publish_service`)."""
        answer = self.publish_service(name, type, url, attributes, service_id=service_id, ttl=ttl)
        return answer["id"]

    def publish_service(
        self,
        name: str,
        type: str,
        url: str | None = None,
        attributes: Mapping[str, AttrValue] | None = None,
        *,
        service_id: str | None = None,
        ttl: float | None = None,
    ) -> Published:
        """Publish a service of this robot; the daemon's answer (id, service, version, ttl,
        expires).

        The id is chosen here (`service_id`, or a fresh one) and sent with the service, so the
        publish is idempotent: when the daemon cannot be reached or the answer is lost, it is
        sent again, and a daemon that stored it already answers 200 instead of storing it
        twice. With `ttl` (seconds) it is a lease: renew it (`renew`), or let `lease` do it.
        """
        return self.call(calls.publish(name, type, url, attributes, service_id, ttl))

    def unpublish(self, service_id: str) -> None:
        self.call(calls.unpublish(service_id))

    def service(self, service_id: str) -> Published:
        """One of this robot's registrations, with its lease."""
        return self.call(calls.service(service_id))

    def renew(self, service_id: str, ttl: float | None = None) -> Renewed:
        """Renew a lease: it runs its ttl (or `ttl`) from now again."""
        return self.call(calls.renew(service_id, ttl))

    def lease(
        self,
        name: str,
        type: str,
        url: str | None = None,
        attributes: Mapping[str, AttrValue] | None = None,
        *,
        ttl: float,
        service_id: str | None = None,
    ) -> KeptLease:
        """Publish a service with a lease and keep renewing it from a thread, until `close()`
        (or the end of a `with` block) unpublishes it. If this program dies, the service is
        withdrawn from the fleet `ttl` seconds later."""
        sid = service_id or new_service_id()
        body = service_body(name, type, url, attributes, sid, ttl)
        self.call(calls.publish(name, type, url, attributes, sid, ttl))
        return KeptLease(self._twin(), body, ttl)

    def services(self) -> list[JsonObject]:
        """This robot's registrations (with their leases' ttl and end)."""
        return self.call(calls.services())

    def neighbors(self, include_unreachable: bool = False) -> list[JsonObject]:
        """The robots reachable now (with `include_unreachable`, all of the history map)."""
        return self.call(calls.neighbors(include_unreachable))

    def search(
        self,
        type: str | None = None,
        attrs: Mapping[str, AttrValue] | None = None,
        **more_attrs: AttrValue,
    ) -> list[JsonObject]:
        """Reachable robots with a service of `type` whose attributes match the given ones
        (numbers by value, booleans as true/false, text exactly).

        Each robot lists only its matching services. Attributes as keywords
        (`search("camera", fps=30)`) or, for any key, as `attrs={"frame-rate": 30}`.
        """
        return self.call(calls.search(type, {**(attrs or {}), **more_attrs}))

    def history(self) -> list[JsonObject]:
        """Every robot ever seen, reachable or not."""
        return self.call(calls.history())

    def self_info(self) -> JsonObject:
        return self.call(calls.self_info())

    def health(self) -> Health:
        """`status` is "ok", or "degraded" (HTTP 503) while the discovery layer is down."""
        return self.call(calls.health())

    def metrics(self) -> str:
        return self.call(calls.metrics())

    def events(self, since: int | None = 0, kinds: Iterable[str] | None = None) -> EventsPage:
        """The changes kept after `since` (0: all of them), at once; ask again from
        `last_id`. `kinds`: only these (e.g. `["robot.appeared", "service"]`)."""
        return self.call(calls.events(since, kinds))

    def watch(
        self,
        kinds: Iterable[str] | None = None,
        since: int | None = None,
        *,
        reconnect: bool = True,
        on_open: Callable[[], object] | None = None,
    ) -> Iterator[Change]:
        """Changes as they happen (GET /events as Server-Sent Events), forever.

        `since`: start after this event id (None: with the next change). When the daemon
        restarts or the stream breaks, it connects again and resumes after the last change
        seen (with `reconnect`; the first connection must work). A `resync` change means
        some were lost: read the state again. `on_open` is called each time the stream is
        (re)opened, before its first change: the moment to read the state a watcher follows.
        """
        cursor = since
        kinds = list(kinds or ())
        first = True
        delay = 0.2
        while True:
            conn = self._connection(STREAM_IDLE)
            headers = {**request_headers(self.owner_token, self.api_token), **STREAM_HEADERS}
            if cursor is not None:
                headers["Last-Event-ID"] = str(cursor)
            try:
                conn.request("GET", calls.events_path(None, kinds), headers=headers)
                resp = conn.getresponse()
                if resp.status != 200:
                    data = resp.read()
                    calls.answer(
                        calls.events(), resp.status, resp.getheader("Content-Type", ""), data
                    )
                first = False
                if on_open is not None:
                    on_open()
                parser = SseParser()
                while raw := resp.readline():
                    done = parser.feed(raw.decode("utf-8", errors="replace").rstrip("\r\n"))
                    if done is not None:
                        change = calls.change(done[1])
                        cursor = change.id
                        delay = 0.2
                        yield change
            except (OSError, http.client.HTTPException) as exc:
                if first or not reconnect:
                    raise self._unreachable(exc) from None
            finally:
                conn.close()
            if not reconnect:
                return
            time.sleep(delay)
            delay = min(5.0, delay * 2)

    # -- the fleet keyring (over the unix socket only) ---------------------------------------

    def keys(self) -> JsonObject:
        """The keyring: mode, the key that signs, and per key its id (never the key)."""
        return self.call(calls.keys())

    def install_key(self, key: bytes) -> JsonObject:
        """Accept `key` from now on (and, for a robot that had no key, sign with it in mode
        accept); the answer has its `id`."""
        return self.call(calls.install_key(base64.b64encode(key).decode()))

    def use_key(self, key_id: str) -> JsonObject:
        return self.call(calls.use_key(key_id))

    def remove_key(self, key_id: str, open_fleet: bool = False) -> None:
        self.call(calls.remove_key(key_id, open_fleet))

    def set_key_mode(self, mode: str) -> JsonObject:
        return self.call(calls.set_key_mode(mode))


class KeptLease:
    """A registration with a lease, renewed from a thread each RENEW_EVERY of its ttl, and
    published again (same id) if it ran out meanwhile (sdfrd was down longer than the ttl).
    `close()` stops renewing and unpublishes it."""

    def __init__(self, client: Client, body: JsonObject, ttl: float) -> None:
        self.id: str = body["id"]
        self.ttl = ttl
        self._client = client
        self._body = body
        self._stop = threading.Event()
        #: The last renewal's failure (None after a success).
        self.error: ApiError | None = None
        self.renewals = 0
        self._thread = threading.Thread(target=self._run, name=f"sdfr-lease-{self.id}")
        self._thread.daemon = True
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.ttl * RENEW_EVERY):
            try:
                try:
                    self._client.call(calls.renew(self.id))
                except ApiError as exc:
                    if exc.status != 404:
                        raise
                    self._client.call(Call("POST", "/services", dict, self._body))
                self.renewals += 1
                self.error = None
            except ApiError as exc:  # sdfrd restarting: the next period tries again
                self.error = exc

    def close(self) -> None:
        """Stop renewing and unpublish (quietly if it is gone already)."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join()
        try:
            self._client.call(calls.unpublish(self.id))
        except ApiError as exc:
            if exc.status != 404:
                raise
        finally:
            self._client.close()

    def __enter__(self) -> KeptLease:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
