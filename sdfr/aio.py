"""An asyncio client of sdfrd's REST API, on aiohttp: the calls of `sdfr.client.Client`, and
live changes in the zeroconf style.

    async with AsyncClient() as sdfr:                       # 127.0.0.1:8700
        await sdfr.publish("front camera", "camera/rgb", attributes={"fps": 30})
        async with sdfr.lease("arm", "actuator/arm", ttl=10):   # renewed by a task
            async for change in sdfr.watch(["robot"]):
                print(change.event, change.robot_id)

Both clients are made of the call definitions of `sdfr.calls`: only the transport differs.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
from collections.abc import AsyncIterator, Callable, Iterable, Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, TypeVar

import aiohttp

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
    new_owner_token,
    new_service_id,
    request_headers,
    service_body,
    split_api,
)
from sdfr.config import DEFAULT_API
from sdfr.errors import ApiError
from sdfr.model import AttrValue

T = TypeVar("T")

__all__ = ["AsyncClient", "AsyncKeptLease", "Change"]


def _reason(exc: BaseException) -> str:
    if isinstance(exc, asyncio.TimeoutError | TimeoutError):
        return "timed out"
    if isinstance(exc, aiohttp.ClientConnectorError):
        return exc.os_error.strerror or str(exc.os_error)
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc) or type(exc).__name__


class AsyncClient:
    """sdfrd's REST API for asyncio; every method raises ApiError (status 0: the daemon was
    not reached). One aiohttp session per client; close it (or use `async with`)."""

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
        self.retry_delays = tuple(retry_delays)
        #: What this client publishes belongs to this token (see `sdfr.client.Client`).
        self.owner_token = owner_token or new_owner_token()
        self.api_token = api_token
        self._unix = None if unix_socket is None else str(unix_socket)
        if self._unix is not None:
            self.where = self._unix
            self._base = "http://localhost"
        else:
            host, port = split_api(api)
            self.where = f"{host}:{port}"
            self._base = f"http://{host if ':' not in host else f'[{host}]'}:{port}"
        self._session: aiohttp.ClientSession | None = None

    # -- plumbing ----------------------------------------------------------------------------

    def _http(self) -> aiohttp.ClientSession:
        if self._session is None:
            connector = aiohttp.UnixConnector(path=self._unix) if self._unix is not None else None
            self._session = aiohttp.ClientSession(
                connector=connector, timeout=aiohttp.ClientTimeout(total=self.timeout)
            )
        return self._session

    async def close(self) -> None:
        if self._session is not None:
            await self._session.close()
            self._session = None

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    def _unreachable(self, exc: BaseException) -> ApiError:
        return calls.unreachable(self.where, _reason(exc), self._unix is not None)

    async def _exchange(self, call: Call[Any]) -> tuple[int, str, bytes]:
        headers = request_headers(self.owner_token, self.api_token)
        try:
            async with self._http().request(
                call.method, self._base + call.path, json=call.body, headers=headers
            ) as resp:
                return resp.status, resp.headers.get("Content-Type", ""), await resp.read()
        except (aiohttp.ClientError, OSError, asyncio.TimeoutError) as exc:
            raise self._unreachable(exc) from None

    async def call(self, call: Call[T]) -> T:
        """Carry out one call of `sdfr.calls` (as `Client.call`)."""
        delays = self.retry_delays if call.retry_unreachable else ()
        for delay in (*delays, None):
            try:
                status, ctype, data = await self._exchange(call)
            except ApiError:
                if delay is None:
                    raise
                await asyncio.sleep(delay)
                continue
            return calls.answer(call, status, ctype, data)
        raise AssertionError("unreachable")

    async def request(
        self, method: str, path: str, body: Any = None, *, accept: tuple[int, ...] = ()
    ) -> Any:
        """One call of any path: the decoded JSON answer (None when empty)."""
        return await self.call(Call(method, path, lambda answer: answer, body, accept))

    # -- the API (as Client's) -----------------------------------------------------------------

    async def publish(
        self,
        name: str,
        type: str,
        url: str | None = None,
        attributes: Mapping[str, AttrValue] | None = None,
        *,
        service_id: str | None = None,
        ttl: float | None = None,
    ) -> str:
        answer = await self.publish_service(
            name, type, url, attributes, service_id=service_id, ttl=ttl
        )
        return answer["id"]

    async def publish_service(
        self,
        name: str,
        type: str,
        url: str | None = None,
        attributes: Mapping[str, AttrValue] | None = None,
        *,
        service_id: str | None = None,
        ttl: float | None = None,
    ) -> Published:
        return await self.call(calls.publish(name, type, url, attributes, service_id, ttl))

    async def unpublish(self, service_id: str) -> None:
        await self.call(calls.unpublish(service_id))

    async def service(self, service_id: str) -> Published:
        return await self.call(calls.service(service_id))

    async def renew(self, service_id: str, ttl: float | None = None) -> Renewed:
        return await self.call(calls.renew(service_id, ttl))

    def lease(
        self,
        name: str,
        type: str,
        url: str | None = None,
        attributes: Mapping[str, AttrValue] | None = None,
        *,
        ttl: float,
        service_id: str | None = None,
    ) -> AsyncKeptLease:
        """`async with client.lease(...) as kept:` publishes with a lease, renews it from a
        task, and unpublishes at the end of the block."""
        sid = service_id or new_service_id()
        return AsyncKeptLease(self, service_body(name, type, url, attributes, sid, ttl), ttl)

    async def services(self) -> list[JsonObject]:
        return await self.call(calls.services())

    async def neighbors(self, include_unreachable: bool = False) -> list[JsonObject]:
        return await self.call(calls.neighbors(include_unreachable))

    async def search(
        self,
        type: str | None = None,
        attrs: Mapping[str, AttrValue] | None = None,
        **more_attrs: AttrValue,
    ) -> list[JsonObject]:
        return await self.call(calls.search(type, {**(attrs or {}), **more_attrs}))

    async def history(self) -> list[JsonObject]:
        return await self.call(calls.history())

    async def self_info(self) -> JsonObject:
        return await self.call(calls.self_info())

    async def health(self) -> Health:
        return await self.call(calls.health())

    async def metrics(self) -> str:
        return await self.call(calls.metrics())

    async def events(self, since: int | None = 0, kinds: Iterable[str] | None = None) -> EventsPage:
        return await self.call(calls.events(since, kinds))

    async def watch(
        self,
        kinds: Iterable[str] | None = None,
        since: int | None = None,
        *,
        reconnect: bool = True,
        on_open: Callable[[], object] | None = None,
    ) -> AsyncIterator[Change]:
        """`async for change in client.watch(...)`: changes as they happen (see
        `Client.watch`), resuming after the last one seen when the stream breaks; `on_open`
        is called each time the stream is (re)opened."""
        cursor = since
        kinds = list(kinds or ())
        first = True
        delay = 0.2
        timeout = aiohttp.ClientTimeout(total=None, sock_read=STREAM_IDLE, connect=self.timeout)
        while True:
            headers = {**request_headers(self.owner_token, self.api_token), **STREAM_HEADERS}
            if cursor is not None:
                headers["Last-Event-ID"] = str(cursor)
            try:
                url = self._base + calls.events_path(None, kinds)
                async with self._http().get(url, headers=headers, timeout=timeout) as resp:
                    if resp.status != 200:
                        calls.answer(
                            calls.events(),
                            resp.status,
                            resp.headers.get("Content-Type", ""),
                            await resp.read(),
                        )
                    first = False
                    if on_open is not None:
                        on_open()
                    parser = SseParser()
                    while raw := await resp.content.readline():
                        done = parser.feed(raw.decode("utf-8", errors="replace").rstrip("\r\n"))
                        if done is not None:
                            change = calls.change(done[1])
                            cursor = change.id
                            delay = 0.2
                            yield change
            except (aiohttp.ClientError, OSError, asyncio.TimeoutError) as exc:
                if first or not reconnect:
                    raise self._unreachable(exc) from None
            if not reconnect:
                return
            await asyncio.sleep(delay)
            delay = min(5.0, delay * 2)

    async def keys(self) -> JsonObject:
        return await self.call(calls.keys())

    async def install_key(self, key: bytes) -> JsonObject:
        return await self.call(calls.install_key(base64.b64encode(key).decode()))

    async def use_key(self, key_id: str) -> JsonObject:
        return await self.call(calls.use_key(key_id))

    async def remove_key(self, key_id: str, open_fleet: bool = False) -> None:
        await self.call(calls.remove_key(key_id, open_fleet))

    async def set_key_mode(self, mode: str) -> JsonObject:
        return await self.call(calls.set_key_mode(mode))


class AsyncKeptLease:
    """A registration with a lease renewed by a task (see `sdfr.client.KeptLease`)."""

    def __init__(self, client: AsyncClient, body: JsonObject, ttl: float) -> None:
        self.id: str = body["id"]
        self.ttl = ttl
        self._client = client
        self._body = body
        self._task: asyncio.Task[None] | None = None
        self.error: ApiError | None = None
        self.renewals = 0

    async def __aenter__(self) -> AsyncKeptLease:
        await self._client.call(Call("POST", "/services", dict, self._body, (), True))
        self._task = asyncio.get_running_loop().create_task(self._run())
        return self

    async def _run(self) -> None:
        while True:
            await asyncio.sleep(self.ttl * RENEW_EVERY)
            try:
                try:
                    await self._client.call(calls.renew(self.id))
                except ApiError as exc:
                    if exc.status != 404:
                        raise
                    await self._client.call(Call("POST", "/services", dict, self._body))
                self.renewals += 1
                self.error = None
            except ApiError as exc:
                self.error = exc

    async def close(self) -> None:
        """Stop renewing and unpublish (quietly if it is gone already)."""
        if self._task is None:
            return
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task
        self._task = None
        try:
            await self._client.call(calls.unpublish(self.id))
        except ApiError as exc:
            if exc.status != 404:
                raise

    async def __aexit__(self, *exc: object) -> None:
        await self.close()
