"""Both Python clients behind one interface, so that one test suite runs against both: the
`connect` fixture gives `sdfr.client.Client` or an `sdfr.aio.AsyncClient` driven from a loop
of its own thread (`Blocking`: each call waits for its coroutine, a lease is awaited when it
is made, a watch is iterated change by change)."""

from __future__ import annotations

import asyncio
import inspect
import threading
from collections.abc import AsyncIterator, Callable, Coroutine, Iterator
from typing import Any, TypeVar

import pytest

from sdfr.aio import AsyncClient, AsyncKeptLease
from sdfr.client import Client

T = TypeVar("T")


class Blocking:
    """An AsyncClient with the sync client's interface."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True)
        self._thread.start()
        self.client = AsyncClient(*args, **kwargs)

    def wait(self, coro: Coroutine[Any, Any, T]) -> T:
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result()

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self.client, name)
        if not callable(attr):
            return attr

        def method(*args: Any, **kwargs: Any) -> Any:
            out = attr(*args, **kwargs)
            if inspect.iscoroutine(out):
                return self.wait(out)
            if isinstance(out, AsyncKeptLease):
                return BlockingLease(self, out)
            if inspect.isasyncgen(out):
                return self._iterate(out)
            return out

        return method

    def _iterate(self, changes: AsyncIterator[Any]) -> Iterator[Any]:
        try:
            while True:
                try:
                    yield self.wait(changes.__anext__())  # type: ignore[arg-type]
                except StopAsyncIteration:
                    return
        finally:
            self.wait(changes.aclose())  # type: ignore[attr-defined]

    def close(self) -> None:
        """As `Client.close`: the connections closed, the client still usable."""
        self.wait(self.client.close())

    def __enter__(self) -> Blocking:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join()
        self._loop.close()


class BlockingLease:
    """An AsyncKeptLease, awaited (published) when made, as `Client.lease` publishes."""

    def __init__(self, owner: Blocking, kept: AsyncKeptLease) -> None:
        self._owner = owner
        self.kept = owner.wait(_opened(kept))

    def __getattr__(self, name: str) -> Any:
        return getattr(self.kept, name)

    def close(self) -> None:
        self._owner.wait(self.kept.close())

    def __enter__(self) -> BlockingLease:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


async def _opened(kept: AsyncKeptLease) -> AsyncKeptLease:
    return await kept


@pytest.fixture(params=["sync", "async"])
def connect(request: pytest.FixtureRequest) -> Callable[..., Any]:
    """Makes a client (the arguments of `Client`): the sync one, or the asyncio one."""
    return Client if request.param == "sync" else Blocking
