"""An asyncio client of sdfrd's REST API, on aiohttp (the `aio` extra): the methods of
`sdfr.client.Client`, and live changes in the zeroconf style.

    async with AsyncClient() as sdfr:                       # 127.0.0.1:8700
        await sdfr.publish("front camera", "camera/rgb", attributes={"fps": 30})
        async with sdfr.lease("arm", "actuator/arm", ttl=10):   # renewed by a task
            async for change in sdfr.watch(["robot"]):
                print(change.event, change.robot_id)

Both clients are `sdfr.client.core.Api` (every call written once, in `sdfr.client.calls`): only the
transport differs.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Generator
from typing import Any, TypeVar

from sdfr import need_extra
from sdfr.client import calls
from sdfr.client.calls import STREAM_IDLE, Call, Change
from sdfr.client.core import (
    Api,
    AsyncTransport,
    Lease,
    LeaseKeeping,
    Plan,
    Stepper,
    Watch,
    attempts,
)
from sdfr.errors import ApiError

try:
    import aiohttp
except ImportError as exc:  # (the dev extra installs it)
    raise ImportError(need_extra("aio", "sdfr.aio", "aiohttp"), name=exc.name) from exc

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


#: What aiohttp raises when sdfrd cannot be reached or the connection breaks.
_BROKEN = (aiohttp.ClientError, OSError, asyncio.TimeoutError)


class AsyncClient(Api, AsyncTransport["AsyncKeptLease"]):
    """sdfrd's REST API for asyncio; every method raises ApiError (status 0: the daemon was
    not reached). One aiohttp session per client; close it (or use `async with`)."""

    _session: aiohttp.ClientSession | None = None

    # -- plumbing ----------------------------------------------------------------------------

    def _base(self) -> str:
        if self._unix is not None:
            return "http://localhost"
        host = self._host if ":" not in self._host else f"[{self._host}]"
        return f"http://{host}:{self._port}"

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

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def _send(self, call: Call[T]) -> T:
        try:
            async with self._http().request(
                call.method, self._base() + call.path, json=call.body, headers=self._headers()
            ) as resp:
                status, ctype = resp.status, resp.headers.get("Content-Type", "")
                data = await resp.read()
        except _BROKEN as exc:
            raise self._unreachable(_reason(exc)) from None
        return calls.answer(call, status, ctype, data)

    async def _run(self, plan: Plan[T]) -> T:
        run = Stepper(plan)
        while run.effect is not None:
            if not isinstance(run.effect, Call):
                await asyncio.sleep(run.effect)
                run.give(None)
                continue
            try:
                value = await self._send(run.effect)
            except ApiError as exc:
                run.fail(exc)
                continue
            run.give(value)
        return run.result

    async def call(self, call: Call[T]) -> T:
        """Carry out one call of `sdfr.client.calls` (as `Client.call`)."""
        return await self._run(attempts(call, self.retry_delays))

    def _carry(self, made: Any) -> Any:
        if isinstance(made, Call):
            return self.call(made)
        if isinstance(made, Lease):
            return AsyncKeptLease(self, made)
        return self._follow(made)

    async def _follow(self, watch: Watch) -> AsyncIterator[Change]:
        timeout = aiohttp.ClientTimeout(total=None, sock_read=STREAM_IDLE, connect=self.timeout)
        url = self._base() + watch.path
        while True:
            try:
                headers = watch.headers(self._headers())
                async with self._http().get(url, headers=headers, timeout=timeout) as resp:
                    if resp.status != 200:
                        ctype = resp.headers.get("Content-Type", "")
                        watch.refused(resp.status, ctype, await resp.read())
                    watch.opened()
                    while raw := await resp.content.readline():
                        if (change := watch.line(raw)) is not None:
                            yield change
            except _BROKEN as exc:
                watch.broken(self._unreachable(_reason(exc)))
            pause = watch.pause()
            if pause is None:
                return
            await asyncio.sleep(pause)


class AsyncKeptLease(LeaseKeeping):
    """A registration with a lease (`AsyncClient.lease`), renewed by a task (see
    `sdfr.client.KeptLease`). Published when awaited, which `async with` does:
    `kept = await client.lease(...)` then `await kept.close()`, or
    `async with client.lease(...) as kept:`."""

    def __init__(self, client: AsyncClient, lease: Lease) -> None:
        super().__init__(lease)
        self._client = client
        self._task: asyncio.Task[None] | None = None

    async def _open(self) -> AsyncKeptLease:
        if self._task is None:
            await self._client.call(self.lease.publish)
            self._task = asyncio.get_running_loop().create_task(self._keep())
        return self

    def __await__(self) -> Generator[Any, None, AsyncKeptLease]:
        return self._open().__await__()

    async def __aenter__(self) -> AsyncKeptLease:
        return await self._open()

    async def _keep(self) -> None:
        while True:
            await asyncio.sleep(self.period)
            try:
                await self._client._run(self.renewal())
            except ApiError as exc:
                self.renewed(exc)
            else:
                self.renewed()

    async def close(self) -> None:
        """Stop renewing and unpublish (quietly if it is gone already)."""
        if self._task is None:
            return
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task
        self._task = None
        await self._client._run(self.withdrawal())

    async def __aexit__(self, *exc: object) -> None:
        await self.close()
