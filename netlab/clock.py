"""Time for the scenario engine: the real clock, or a virtual one a test drives.

The engine reads time and waits only through a `Clock`, and samples the fleet with
`Clock.every`; a `VirtualClock` makes a whole scenario (minutes of mobility, the
product's 10 s beacon) run against a fake lab in an instant, the same discipline as
`sdfr.protocol`'s core in `sdfr/testing/simnet.py`.
"""

from __future__ import annotations

import heapq
import itertools
import threading
import time
from collections.abc import Callable
from typing import Protocol

Stop = Callable[[], None]


class Clock(Protocol):
    def monotonic(self) -> float:
        """Seconds for intervals and deadlines."""
        ...

    def time(self) -> float:
        """UNIX seconds: the clock of the pcaps, samples and reports."""
        ...

    def sleep(self, seconds: float) -> None: ...

    def every(self, period: float, fn: Callable[[], None]) -> Stop:
        """Call `fn` every `period` seconds (first after one period) until the returned
        function is called; that call waits for a call under way to end."""
        ...


class RealClock:
    """The machine's clocks; `every` runs `fn` in a daemon thread."""

    def monotonic(self) -> float:
        return time.monotonic()

    def time(self) -> float:
        return time.time()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)

    def every(self, period: float, fn: Callable[[], None]) -> Stop:
        if period <= 0:
            raise ValueError(f"period must be positive, not {period}")
        stop = threading.Event()

        def loop() -> None:
            while not stop.wait(period):
                fn()

        thread = threading.Thread(target=loop, name="netlab-every", daemon=True)
        thread.start()

        def cancel() -> None:
            stop.set()
            if thread is not threading.current_thread():
                thread.join()

        return cancel


REAL = RealClock()


class VirtualClock:
    """Time that moves only when the code under test sleeps; timers fire in order."""

    def __init__(self, epoch: float = 1_800_000_000.0) -> None:
        self.now = 0.0
        self.epoch = epoch
        self._timers: list[tuple[float, int, float, Callable[[], None]]] = []
        self._cancelled: set[int] = set()
        self._ids = itertools.count()

    def monotonic(self) -> float:
        return self.now

    def time(self) -> float:
        return self.epoch + self.now

    def sleep(self, seconds: float) -> None:
        end = self.now + max(0.0, seconds)
        while self._timers and self._timers[0][0] <= end:
            due, tid, period, fn = heapq.heappop(self._timers)
            if tid in self._cancelled:
                continue
            self.now = max(self.now, due)
            heapq.heappush(self._timers, (due + period, tid, period, fn))
            fn()
        self.now = end

    def every(self, period: float, fn: Callable[[], None]) -> Stop:
        if period <= 0:
            raise ValueError(f"period must be positive, not {period}")
        tid = next(self._ids)
        heapq.heappush(self._timers, (self.now + period, tid, period, fn))
        return lambda: self._cancelled.add(tid)
