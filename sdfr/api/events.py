"""GET /events: the store's event log, as Server-Sent Events to every subscriber.

The changes are seen by the process that makes them: the discovery layer (robots) and this
one (local registrations), and both append them to the store's event log in the transaction
that stores the change (`sdfr.store`). The hub reads what is new when it is woken: by the
writer of this process after a commit, by the discovery layer's datagram on the status socket
after one of its commits, and, in case such a datagram was lost, by a poll once a second
while anyone listens. It keeps the newest events in memory, so that a hundred subscribers cost
one query; a subscriber further behind reads the log itself.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from collections import deque
from collections.abc import AsyncIterator

from sdfr.api.doors import client_identity
from sdfr.api.http import Request, Response, StreamResponse
from sdfr.api.replies import RequestError, json_response
from sdfr.api.state import state_of
from sdfr.errors import ValidationError
from sdfr.records.events import kind_filter
from sdfr.store import Store, StoredEvent

#: Event streams open at once; more are refused (503) so that the API keeps its descriptors.
STREAMS_MAX = 64
#: Event streams one client (a user: see sdfr.api.doors.client_identity) may hold; more are
#: refused (429) so that one program cannot take them all. Root's are not counted: root can
#: stop the daemon anyway.
STREAMS_PER_CLIENT = STREAMS_MAX // 4
#: A comment line this often keeps proxies and idle timers from closing a quiet stream.
KEEPALIVE = 15.0
#: While anyone listens, the log is looked at this often even without a wake-up.
POLL = 1.0
#: Newest events held in memory.
RING = 1024
#: Events one JSON answer (not a stream) holds at most; `last_id` says where to go on.
PAGE = 256
SSE = "text/event-stream"


class EventHub:
    """The newest events of the log, and the streams following it."""

    def __init__(self, store: Store) -> None:
        self.store = store
        self.last_id = store.last_event_id()
        self._ring: deque[StoredEvent] = deque()
        #: The ring holds every event with an id above this one.
        self._ring_from = self.last_id
        self._news = asyncio.Event()
        self._closing = asyncio.Event()
        self._listened = asyncio.Event()  # set while streams are open: the poll runs
        self.streams = 0
        #: Streams open by client (sdfr.api.doors.client_identity).
        self.by_client: dict[str, int] = {}
        self.reads = 0  # queries of the log made by the hub (for the benchmark)

    def wake(self) -> None:
        """Read what is new in the log, and tell the streams."""
        if self.store.last_event_id() <= self.last_id:
            return
        while True:
            batch = self.store.events_after(self.last_id, PAGE)
            self.reads += 1
            for event in batch:
                if len(self._ring) >= RING:
                    self._ring_from = self._ring.popleft().id
                self._ring.append(event)
                self.last_id = event.id
            if len(batch) < PAGE:
                break
        news, self._news = self._news, asyncio.Event()
        news.set()

    async def closing(self, timeout: float, gone: asyncio.Event | None = None) -> bool:
        """Wait up to `timeout` seconds for the server to stop (or `gone` to be set: the
        client went away); True when either happened."""
        waits = [asyncio.ensure_future(self._closing.wait())]
        if gone is not None:
            waits.append(asyncio.ensure_future(gone.wait()))
        try:
            done, _ = await asyncio.wait(waits, timeout=timeout, return_when="FIRST_COMPLETED")
        finally:
            for w in waits:
                w.cancel()
        return bool(done)

    def close(self) -> None:
        """The server stops: every stream ends."""
        self._closing.set()
        self._news.set()
        self._listened.set()

    def opened(self, client: str = "") -> None:
        """A stream starts following the log (for `client`)."""
        self.streams += 1
        self.by_client[client] = self.by_client.get(client, 0) + 1
        self._listened.set()

    def closed(self, client: str = "") -> None:
        self.streams -= 1
        left = self.by_client.get(client, 1) - 1
        if left:
            self.by_client[client] = left
        else:
            self.by_client.pop(client, None)
        if not self.streams:
            self._listened.clear()

    async def poll(self) -> None:
        """Wake the hub once a POLL while anyone listens (a lost wake-up costs 1 s at most);
        while nobody does, sleep until someone does (an idle API has no timer of its own)."""
        while not self._closing.is_set():
            await self._listened.wait()
            await asyncio.sleep(POLL)
            if self.streams:
                self.wake()

    def _after(self, cursor: int) -> list[StoredEvent]:
        if cursor >= self.last_id:
            return []
        if cursor >= self._ring_from:
            return [e for e in self._ring if e.id > cursor]
        return self.store.events_after(cursor, PAGE)

    def start_at(self, after: int | None) -> tuple[int, StoredEvent | None]:
        """Where a reader asking for events after `after` (None: only new ones) starts, and
        the resync event it gets first when some of those events are no longer kept (or the
        id is not one of this log: a state directory started afresh)."""
        if after is None:
            return self.last_id, None
        if after < self.store.events_pruned() or after > self.last_id:
            body = json.dumps(
                {
                    "id": self.last_id,
                    "event": "resync",
                    "time": round(time.time(), 6),
                    "robot_id": None,
                    "after": after,
                },
                separators=(",", ":"),
            )
            return self.last_id, StoredEvent(self.last_id, "resync", body)
        return after, None

    async def follow(
        self, after: int | None, gone: asyncio.Event | None = None
    ) -> AsyncIterator[StoredEvent | None]:
        """The events after `after`, then each new one as it comes; None each KEEPALIVE of
        silence. Ends when the server stops, or `gone` is set (the client went away: its
        place is free at once, not at the next keep-alive)."""
        cursor, first = self.start_at(after)
        if first is not None:
            yield first
        while not self._closing.is_set():
            batch = self._after(cursor)
            for event in batch:
                yield event
                cursor = event.id
            if batch:
                continue
            waits = [asyncio.ensure_future(self._news.wait())]
            if gone is not None:
                waits.append(asyncio.ensure_future(gone.wait()))
            try:
                done, _ = await asyncio.wait(
                    waits, timeout=KEEPALIVE, return_when="FIRST_COMPLETED"
                )
            finally:
                for w in waits:
                    w.cancel()
            if gone is not None and gone.is_set():
                return
            if not done:
                yield None


#: The largest event id (SQLite's INTEGER).
ID_MAX = 2**63 - 1


def _event_id(name: str, raw: str | None) -> int | None:
    if raw is None:
        return None
    if not raw.isdigit() or len(raw) > 19 or int(raw) > ID_MAX:
        raise ValidationError(name, "must be an event id (a whole number, 0 for the oldest kept)")
    return int(raw)


def _after(request: Request) -> int | None:
    """Where to start: the Last-Event-ID header (a reconnecting EventSource's), else `since`."""
    since = _event_id("since", request.query.get("since"))
    header = _event_id("Last-Event-ID", request.headers.get("Last-Event-ID"))
    return header if header is not None else since


def _kinds(request: Request) -> frozenset[str] | None:
    names = request.query.getall("event", [])
    if not names:
        return None
    try:
        return kind_filter(n for name in names for n in name.split(",") if n)
    except ValueError as exc:
        raise ValidationError("event", str(exc)) from None


def _sse(event: StoredEvent) -> bytes:
    return f"id: {event.id}\nevent: {event.kind}\ndata: {event.body}\n\n".encode()


async def events(request: Request) -> Response:
    """GET /events: a stream of Server-Sent Events when the client accepts
    text/event-stream, else the events after `since` at once, as JSON."""
    for key in request.query:
        if key not in ("since", "event"):
            raise ValidationError(key, "unknown query parameter (known: event, since)")
    state = state_of(request)
    hub = state.hub
    hub.wake()  # (a wake-up may have been lost while nobody listened)
    after = _after(request)
    kinds = _kinds(request)
    if SSE not in request.headers.get("Accept", ""):
        if after is None:  # only new ones: none yet; last_id is where they will start
            return json_response(f'{{"events":[],"last_id":{hub.last_id}}}'.encode())
        cursor, first = hub.start_at(after)
        found = [] if first is None else [first]
        found += hub.store.events_after(cursor, PAGE)
        chosen = [e for e in found if kinds is None or e.kind in kinds or e.kind == "resync"]
        last = found[-1].id if found else cursor
        body = '{"events":[' + ",".join(e.body for e in chosen) + f'],"last_id":{last}}}'
        return json_response(body.encode())
    if hub.streams >= STREAMS_MAX:
        raise RequestError(
            503, f"{STREAMS_MAX} event streams are open already; close one", "events"
        )
    client, uid = client_identity(request)
    held = hub.by_client.get(client, 0)
    if uid != 0 and held >= STREAMS_PER_CLIENT:
        raise RequestError(
            429,
            f"this client ({client}) has {held} event streams open already, the most one client "
            f"may hold ({STREAMS_PER_CLIENT} per client, {STREAMS_MAX} in all); close one",
            "events",
        )
    resp = StreamResponse(
        headers={
            "Content-Type": f"{SSE}; charset=utf-8",
            "Cache-Control": "no-cache",
            "X-Accel-Buffering": "no",
        }
    )
    hub.opened(client)
    try:
        await resp.prepare(request)
        await resp.write(b"retry: 1000\n\n")
        async for event in hub.follow(after, resp.gone):
            if event is None:
                await resp.write(b": keep-alive\n\n")
            elif kinds is None or event.kind in kinds or event.kind == "resync":
                await resp.write(_sse(event))
    except ConnectionError:  # the client went away
        pass
    finally:
        hub.closed(client)
    with contextlib.suppress(ConnectionError):
        await resp.write_eof()
    return resp
