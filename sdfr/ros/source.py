"""Where the bridge learns that the neighbour list may have changed: the seam.

A `ChangeSource` calls `deliver` with the neighbour list each time it may have changed; the
bridge turns consecutive lists (`snapshot.Snapshot`) into change events (`core.diff`), so a
source only has to say "here is the list now".

* `EventStreamSource` (the bridge's default) follows sdfrd's change stream (`GET /events`,
  Server-Sent Events, the robot changes) and reads `GET /neighbors` again on each change,
  after each reconnection, and every `refresh` seconds (the indicator and RTT drift without
  an event).  A sdfrd without the stream (an older one: 404) is polled instead.
* `PollingSource` reads `GET /neighbors` every `interval` seconds.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from http import HTTPStatus
from typing import Protocol

from sdfr.client import Client
from sdfr.errors import ApiError, SdfrError
from sdfr.ros.snapshot import Snapshot, read_snapshot

log = logging.getLogger("sdfr.ros")


class ChangeSource(Protocol):
    def run(self, deliver: Callable[[Snapshot], None], stop: threading.Event) -> None:
        """Call `deliver` with the neighbour list whenever it may have changed (at least once
        soon after the start), until `stop` is set; survive the daemon going away."""
        ...


class _Reader:
    """Reads the neighbour list and hands it on; a failure is logged once until it changes."""

    clock: Callable[[], float]
    #: The last failure to read the list ("" when the last read worked).
    last_error = ""

    def read(self, client: Client, deliver: Callable[[Snapshot], None]) -> None:
        try:
            snapshot = read_snapshot(client, self.clock)
        except (ApiError, SdfrError) as exc:
            if str(exc) != self.last_error:
                log.warning("cannot read the neighbour list: %s", exc)
            self.last_error = str(exc)
        else:
            self.last_error = ""
            deliver(snapshot)


class PollingSource(_Reader):
    """`GET /neighbors` every `interval` seconds, on a client of its own."""

    def __init__(
        self,
        connect: Callable[[], Client],
        interval: float,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.connect = connect
        self.interval = interval
        self.clock = clock

    def run(self, deliver: Callable[[Snapshot], None], stop: threading.Event) -> None:
        with self.connect() as client:
            while not stop.is_set():
                started = time.monotonic()
                self.read(client, deliver)
                stop.wait(max(0.0, self.interval - (time.monotonic() - started)))


class EventStreamSource(_Reader):
    """The neighbour list read again whenever sdfrd's change stream says a robot changed."""

    def __init__(
        self,
        connect: Callable[[], Client],
        fallback: PollingSource,
        refresh: float = 5.0,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.connect = connect
        self.fallback = fallback
        self.refresh = refresh
        self.clock = clock
        #: Whether the stream is followed now (False: not yet, or polling instead).
        self.streaming = False

    def run(self, deliver: Callable[[Snapshot], None], stop: threading.Event) -> None:
        wake = threading.Event()
        unsupported = threading.Event()

        def opened() -> None:  # (re)connected: what happened meanwhile is read again
            self.streaming = True
            wake.set()

        def follow() -> None:
            # Blocks in the stream's reads: a thread of its own, so that `stop` is seen at
            # once below; it ends with the stream, or with the process (a daemon thread).
            while not stop.is_set():
                try:
                    with self.connect() as client:
                        for _change in client.watch(["robot"], on_open=opened):
                            wake.set()
                            if stop.is_set():
                                return
                except ApiError as exc:
                    if exc.status == HTTPStatus.NOT_FOUND:
                        unsupported.set()
                        wake.set()
                        return
                except SdfrError:
                    pass  # no daemon answers yet: try again
                self.streaming = False
                stop.wait(0.5)

        threading.Thread(target=follow, name="sdfr-ros-events", daemon=True).start()
        with self.connect() as client:
            while not stop.is_set():
                if unsupported.is_set():
                    log.info("sdfrd has no change stream (GET /events): polling instead")
                    self.fallback.run(deliver, stop)
                    return
                wake.clear()  # a change from now on is read by the next round
                self.read(client, deliver)
                until = time.monotonic() + self.refresh
                while not (stop.is_set() or wake.is_set()) and time.monotonic() < until:
                    wake.wait(min(0.1, until - time.monotonic()))
