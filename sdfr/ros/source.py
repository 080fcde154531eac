"""Where the bridge learns that the neighbour list may have changed: the seam.

A `ChangeSource` calls `deliver` with the neighbour list each time it may have changed; the
bridge turns consecutive lists into change events (`core.diff`), so a source only has to
say "here is the list now".  `PollingSource` reads `GET /neighbors` every `interval`
seconds.  When sdfrd serves its change stream (`GET /events`, Server-Sent Events), an
`EventStreamSource` reading it -- and reading the list again on each event, or after a
reconnection -- replaces it in `Bridge(source=...)`; neither the core nor the adapters change.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol

from sdfr.client import Client
from sdfr.errors import ApiError, SdfrError

if TYPE_CHECKING:
    from sdfr.ros.core import Snapshot

log = logging.getLogger("sdfr.ros")


class ChangeSource(Protocol):
    def run(self, deliver: Callable[[Snapshot], None], stop: threading.Event) -> None:
        """Call `deliver` with the neighbour list whenever it may have changed (at least once
        soon after the start), until `stop` is set; survive the daemon going away."""
        ...


class PollingSource:
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
        #: The last failure to read the list ("" when the last read worked).
        self.last_error = ""

    def run(self, deliver: Callable[[Snapshot], None], stop: threading.Event) -> None:
        from sdfr.ros.core import read_snapshot

        with self.connect() as client:
            while not stop.is_set():
                started = time.monotonic()
                try:
                    snapshot = read_snapshot(client, self.clock)
                except (ApiError, SdfrError) as exc:
                    if str(exc) != self.last_error:
                        log.warning("cannot read the neighbour list: %s", exc)
                    self.last_error = str(exc)
                else:
                    self.last_error = ""
                    deliver(snapshot)
                stop.wait(max(0.0, self.interval - (time.monotonic() - started)))
