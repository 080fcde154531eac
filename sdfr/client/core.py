"""The clients' core: sdfrd's REST API written once, without I/O, for both transports.

`Api` holds every call of the API as a method (an `Op` made from the call's definition in
`sdfr.client.calls`, whose signature and docstring are the method's). A transport (`sdfr.client`:
http.client in threads; `sdfr.aio`: aiohttp in asyncio) only carries what a method makes:

* a `Call`, sent by running a `Plan` (`attempts`: sent again while sdfrd cannot be reached,
  when the call may be);
* a `Lease`, published, then kept by the transport's kept lease (`LeaseKeeping`: the renewal
  and the withdrawal as plans, the last error, the count of renewals);
* a `Watch`, the event stream: its request, its lines parsed into changes, where it resumes
  and how long to pause before connecting again.

A plan is a generator that yields a `Call` (the transport sends the call's result back, or
throws in its ApiError) or a pause in seconds; `Stepper` steps one for a transport.
"""

from __future__ import annotations

import functools
from collections.abc import (
    AsyncIterator,
    Callable,
    Coroutine,
    Generator,
    Iterable,
    Iterator,
    Mapping,
    Sequence,
)
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Generic, ParamSpec, TypeVar, overload

from sdfr.client import calls
from sdfr.client.calls import (
    RENEW_EVERY,
    RETRY_DELAYS,
    STREAM_HEADERS,
    Call,
    Change,
    JsonObject,
    PublishedJson,
    SseParser,
    Unreachable,
    new_owner_token,
    request_headers,
    split_api,
)
from sdfr.endpoints import DEFAULT_API
from sdfr.errors import ApiError
from sdfr.records.model import AttrValue

P = ParamSpec("P")
T = TypeVar("T")
M = TypeVar("M")
K = TypeVar("K")

#: A step of a plan: a call to send, or a pause (seconds).
Effect = Call[Any] | float
Plan = Generator[Effect, Any, T]


def attempts(call: Call[T], delays: Sequence[float]) -> Plan[T]:
    """Send `call`; when it may be sent again (`retry_unreachable`) and sdfrd could not be
    reached, again after each of `delays`."""
    for delay in delays if call.retry_unreachable else ():
        try:
            result: T = yield call
            return result
        except Unreachable:
            yield delay
    result = yield call
    return result


class Stepper(Generic[T]):
    """A plan, one effect at a time: `effect` is what the transport does next; None when the
    plan is done, and `result` is its outcome (an error it raises goes to the transport)."""

    def __init__(self, plan: Plan[T]) -> None:
        self._plan = plan
        self.effect: Effect | None = None
        self.result: T
        self._step(plan.send, None)

    def _step(self, step: Callable[[Any], Effect], arg: Any) -> None:
        try:
            self.effect = step(arg)
        except StopIteration as stop:
            self.effect = None
            self.result = stop.value

    def give(self, value: Any) -> None:
        """The effect's result (None after a pause)."""
        self._step(self._plan.send, value)

    def fail(self, error: ApiError) -> None:
        """The call failed with `error`."""
        self._step(self._plan.throw, error)


# -- leases ------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Lease:
    """A registration with a lease, as `Api.lease` makes it: its publish and its ttl."""

    publish: Call[PublishedJson]
    ttl: float

    @property
    def id(self) -> str:
        assert self.publish.body is not None
        return str(self.publish.body["id"])


def lease(
    name: str,
    type: str,
    url: str | None = None,
    attributes: Mapping[str, AttrValue] | None = None,
    *,
    ttl: float,
    service_id: str | None = None,
) -> Lease:
    """Publish a service with a lease and keep renewing it (each third of `ttl`, from a
    thread or a task), publishing it again under its id if it ran out meanwhile (sdfrd was
    down longer than the ttl), until the lease is closed (`close()`, or the end of its
    `with` or `async with` block), which unpublishes it. If this program dies, the service
    is withdrawn from the fleet `ttl` seconds later.

    The lease is published when it is made: `Client.lease(...)` before it returns,
    `AsyncClient.lease(...)` when it is awaited (which `async with` does); a publish that
    fails raises ApiError there, and nothing is kept.
    """
    call = calls.publish_service(name, type, url, attributes, service_id=service_id, ttl=ttl)
    return Lease(call, ttl)


class LeaseKeeping:
    """What both kept leases share: the lease, its renewal and withdrawal (plans), and how
    renewing went (`error`: the last renewal's failure, None after a success)."""

    def __init__(self, lease: Lease) -> None:
        self.lease = lease
        self.id = lease.id
        self.ttl = lease.ttl
        self.error: ApiError | None = None
        self.renewals = 0

    @property
    def period(self) -> float:
        """Seconds between renewals."""
        return self.ttl * RENEW_EVERY

    def renewal(self) -> Plan[None]:
        """Renew; published again (once, same id) when sdfrd no longer has it."""
        try:
            yield calls.renew(self.id)
        except ApiError as exc:
            if exc.status != 404:
                raise
            yield replace(self.lease.publish, retry_unreachable=False)

    def renewed(self, error: ApiError | None = None) -> None:
        """A renewal's outcome (a failure: sdfrd restarting, the next period tries again)."""
        self.error = error
        if error is None:
            self.renewals += 1

    def withdrawal(self) -> Plan[None]:
        """Unpublish, quietly if it is gone already."""
        try:
            yield calls.unpublish(self.id)
        except ApiError as exc:
            if exc.status != 404:
                raise


# -- the event stream --------------------------------------------------------------------------


class Watch:
    """GET /events followed as Server-Sent Events (see `watch`): the request, its lines
    parsed into changes, where it resumes and how long to pause before connecting again."""

    def __init__(
        self,
        kinds: Iterable[str] | None,
        since: int | None,
        reconnect: bool,
        on_open: Callable[[], object] | None,
    ) -> None:
        self.cursor = since
        self.path = calls.events_path(None, list(kinds or ()))
        self.reconnect = reconnect
        self.on_open = on_open
        self._first = True
        self._delay = 0.2
        self._parser = SseParser()

    def headers(self, base: Mapping[str, str]) -> dict[str, str]:
        """The request's headers: `base`, the stream's, and where to resume."""
        headers = {**base, **STREAM_HEADERS}
        if self.cursor is not None:
            headers["Last-Event-ID"] = str(self.cursor)
        return headers

    def refused(self, status: int, content_type: str, data: bytes) -> None:
        """An answer other than 200: its error raised."""
        calls.answer(calls.events(), status, content_type, data)

    def opened(self) -> None:
        """The stream is open: what follows is its changes."""
        self._first = False
        if self.on_open is not None:
            self.on_open()
        self._parser = SseParser()

    def line(self, raw: bytes) -> Change | None:
        """One line of the stream; the change it completes, if any."""
        done = self._parser.feed(raw.decode("utf-8", errors="replace").rstrip("\r\n"))
        if done is None:
            return None
        change = calls.change(done[1])
        self.cursor = change.id
        self._delay = 0.2
        return change

    def broken(self, error: ApiError) -> None:
        """The stream could not be opened or broke: `error` raised unless it is followed
        again (it reconnects, and the first connection worked)."""
        if self._first or not self.reconnect:
            raise error from None

    def pause(self) -> float | None:
        """Seconds to wait before connecting again (growing to 5 s); None: stop."""
        if not self.reconnect:
            return None
        delay, self._delay = self._delay, min(5.0, self._delay * 2)
        return delay


def watch(
    kinds: Iterable[str] | None = None,
    since: int | None = None,
    *,
    reconnect: bool = True,
    on_open: Callable[[], object] | None = None,
) -> Watch:
    """Changes as they happen (GET /events as Server-Sent Events), forever: `for change in
    client.watch(...)`, or `async for` with the AsyncClient.

    `since`: start after this event id (None: with the next change). When the daemon
    restarts or the stream breaks, it connects again and resumes after the last change
    seen (with `reconnect`; the first connection must work). A `resync` change means
    some were lost: read the state again. `on_open` is called each time the stream is
    (re)opened, before its first change: the moment to read the state a watcher follows.
    """
    return Watch(kinds, since, reconnect, on_open)


# -- the clients -------------------------------------------------------------------------------


class Transport(Generic[K]):
    """What both clients are given and share: where sdfrd is, the owner token (what the
    client publishes belongs to it; sent with every call), the token of sdfrd's
    api_token_file for an API on another machine. `K` is the transport's kept lease."""

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
        self._unix = None if unix_socket is None else str(unix_socket)
        if self._unix is not None:
            self._host, self._port = "localhost", 0
            self.where = self._unix
        else:
            self._host, self._port = split_api(api)
            self.where = f"{self._host}:{self._port}"

    def _headers(self) -> dict[str, str]:
        return request_headers(self.owner_token, self.api_token)

    def _unreachable(self, reason: str) -> Unreachable:
        return calls.unreachable(self.where, reason, self._unix is not None)

    def _carry(self, made: Any) -> Any:
        """Carry out what a method of `Api` made: a Call, a Lease or a Watch."""
        raise NotImplementedError


class SyncTransport(Transport[K]):
    """A transport whose methods block (`sdfr.client`)."""


class AsyncTransport(Transport[K]):
    """A transport whose calls are awaited (`sdfr.aio`)."""


class Op(Generic[P, M]):
    """A method of both clients, made from `make` (a call definition, `lease` or `watch`):
    its arguments are `make`'s, and the client carries out what `make` returns."""

    def __init__(self, make: Callable[P, M]) -> None:
        self.make = make
        self.__doc__ = make.__doc__

    @overload
    def __get__(self, client: None, owner: type) -> Op[P, M]: ...
    @overload
    def __get__(
        self: Op[P, Call[T]], client: SyncTransport[Any], owner: type
    ) -> Callable[P, T]: ...
    @overload
    def __get__(
        self: Op[P, Call[T]], client: AsyncTransport[Any], owner: type
    ) -> Callable[P, Coroutine[Any, Any, T]]: ...
    @overload
    def __get__(self: Op[P, Lease], client: Transport[K], owner: type) -> Callable[P, K]: ...
    @overload
    def __get__(
        self: Op[P, Watch], client: SyncTransport[Any], owner: type
    ) -> Callable[P, Iterator[Change]]: ...
    @overload
    def __get__(
        self: Op[P, Watch], client: AsyncTransport[Any], owner: type
    ) -> Callable[P, AsyncIterator[Change]]: ...
    def __get__(self, client: Transport[Any] | None, owner: type) -> Any:
        if client is None:
            return self
        make = self.make

        @functools.wraps(make)
        def method(*args: Any, **kwargs: Any) -> Any:
            return client._carry(make(*args, **kwargs))

        return method


class Api:
    """Every call of sdfrd's REST API, as methods of both clients; each raises ApiError
    (status 0: the daemon was not reached)."""

    request = Op(calls.request)
    publish = Op(calls.publish)
    publish_service = Op(calls.publish_service)
    unpublish = Op(calls.unpublish)
    service = Op(calls.service)
    renew = Op(calls.renew)
    lease = Op(lease)
    services = Op(calls.services)
    neighbors = Op(calls.neighbors)
    search = Op(calls.search)
    history = Op(calls.history)
    self_info = Op(calls.self_info)
    health = Op(calls.health)
    metrics = Op(calls.metrics)
    events = Op(calls.events)
    watch = Op(watch)
    keys = Op(calls.keys)
    install_key = Op(calls.install_key)
    use_key = Op(calls.use_key)
    remove_key = Op(calls.remove_key)
    set_key_mode = Op(calls.set_key_mode)


__all__ = ["Api", "JsonObject", "Lease", "LeaseKeeping", "Op", "Stepper", "Watch", "attempts"]
