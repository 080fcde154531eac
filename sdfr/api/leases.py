"""Leases: registrations with a ttl end when their owner stops renewing them.

The store keeps each lease's end as Unix time, so a lease outlives a restart (and one that
ended while the daemon was down is withdrawn at its start). While the API layer runs it
counts on the monotonic clock: a wall clock set forward (a robot's first NTP sync after boot)
must not end every lease at once. An ended lease is withdrawn like an unpublish: the local
version goes up, the discovery layer is woken and tells the fleet, and the event log says
`service.expired`.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable

from sdfr.api.state import Writer
from sdfr.store import Expire, Lease

log = logging.getLogger("sdfr.api")

#: The shortest and longest ttl a registration may have (seconds).
TTL_MIN = 1.0
TTL_MAX = 366 * 86400.0


class Leases:
    """The timer that withdraws registrations whose lease ran out."""

    def __init__(self, writer: Writer, withdrawn: Callable[[list[str]], None]) -> None:
        self.writer = writer
        #: Called with the ids just withdrawn (to wake the discovery layer).
        self.withdrawn = withdrawn
        #: service id -> (monotonic deadline, the end the store holds)
        self._due: dict[str, tuple[float, float]] = {}
        self._timer: asyncio.TimerHandle | None = None
        self._task: asyncio.Task[None] | None = None
        self.expired = 0

    def set(self, lease: Lease | None, service_id: str) -> None:
        """`service_id`'s lease is now `lease` (None: it has none, or is gone)."""
        if lease is None:
            self._due.pop(service_id, None)
        else:
            left = lease.expires - time.time()
            self._due[service_id] = (time.monotonic() + left, lease.expires)
        self._arm()

    def load(self, leases: list[Lease]) -> None:
        for lease in leases:
            self.set(lease, lease.service_id)

    def close(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _arm(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._due and (self._task is None or self._task.done()):
            when = min(d for d, _ in self._due.values())
            loop = asyncio.get_running_loop()
            # loop.time() is time.monotonic() on Linux's default loop.
            self._timer = loop.call_at(when, self._fire)

    def _fire(self) -> None:
        self._timer = None
        self._task = asyncio.get_running_loop().create_task(self._expire())

    async def _expire(self) -> None:
        now = time.monotonic()
        due = [(sid, end) for sid, (at, end) in self._due.items() if at <= now]
        try:
            results = await asyncio.gather(
                *(self.writer.write(Expire(sid, end)) for sid, end in due),
                return_exceptions=True,
            )
        finally:
            self._task = None
        gone = []
        for (sid, end), result in zip(due, results, strict=True):
            if isinstance(result, BaseException):
                log.error("cannot withdraw %s, whose lease ran out: %s", sid, result)
                self._due[sid] = (time.monotonic() + 1.0, end)  # again in a second
                continue
            current = self._due.get(sid)
            if current is not None and current[1] == end:
                del self._due[sid]
            if result is not None:  # (None: renewed or unpublished meanwhile)
                gone.append(sid)
        if gone:
            self.expired += len(gone)
            log.info("lease ran out: withdrew %s", ", ".join(gone))
            self.withdrawn(gone)
        self._arm()
