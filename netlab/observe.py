"""Watching a running fleet live: what each robot's sdfrd lists.

* `Probe` asks the robots' daemons over their REST API (one client per robot; one probe per
  thread, since a client is not shared between threads);
* `Observer` samples the neighbour lists in the background, for the report's plots and the
  agreement check (`netlab.samples` judges the samples, `netlab.judging` a snapshot, both
  against the truth that `netlab.truth.TruthLog` records).

Times are UNIX seconds (``time.time()``), the clock of the pcaps and the report.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, Protocol

import msgspec

from netlab.analysis import natural_order
from netlab.clock import REAL, Clock
from netlab.judging import PeerEntry, View
from netlab.samples import Sample
from netlab.truth import TruthLog
from sdfr.errors import ApiError
from sdfr.records.schema import Neighbor, PeerJson

__all__ = ["ClientLike", "Observer", "Probe"]


class ClientLike(Protocol):
    """What the scenario engine needs of `sdfr.client.Client`."""

    def neighbors(self, include_unreachable: bool = False) -> list[dict[str, Any]]: ...

    def history(self) -> list[dict[str, Any]]: ...

    def publish(
        self,
        name: str,
        type: str,
        url: str | None = None,
        attributes: Mapping[str, Any] | None = None,
    ) -> str: ...

    def unpublish(self, service_id: str) -> None: ...

    def self_info(self) -> dict[str, object]: ...

    def close(self) -> None: ...


class Probe:
    """Asks robots' daemons what they list; errors become a `View` with `error` set."""

    def __init__(self, connect: Callable[[str], ClientLike]) -> None:
        self._connect = connect
        self._clients: dict[str, ClientLike] = {}

    def client(self, robot: str) -> ClientLike:
        if robot not in self._clients:
            self._clients[robot] = self._connect(robot)
        return self._clients[robot]

    def neighbours(self, robots: Iterable[str]) -> dict[str, View]:
        """Each robot's reachable neighbours."""
        return {
            r: self._ask(r, lambda c: msgspec.convert(c.neighbors(), list[Neighbor]))
            for r in robots
        }

    def histories(self, robots: Iterable[str]) -> dict[str, View]:
        """Each robot's history map: every robot it ever heard."""
        return {
            r: self._ask(r, lambda c: msgspec.convert(c.history(), list[PeerJson])) for r in robots
        }

    def addresses(self, robots: Iterable[str]) -> dict[str, str]:
        """Each robot's own address (``GET /self``): "" before it has one, or "error: ..."."""
        out: dict[str, str] = {}
        for robot in robots:
            try:
                out[robot] = str(self.client(robot).self_info().get("address") or "")
            except ApiError as exc:
                out[robot] = f"error: {exc}"
        return out

    def _ask(self, robot: str, call: Callable[[ClientLike], Sequence[Neighbor | PeerJson]]) -> View:
        """`call`'s answer, decoded by the API's schema (`sdfr.records.schema`), as a View; a
        robot that cannot be asked, or answers what the schema does not allow, an error."""
        try:
            found = call(self.client(robot))
        except ApiError as exc:
            return View(error=str(exc))
        except msgspec.ValidationError as exc:
            return View(error=f"its answer does not match the API's schema: {exc}")
        return View(tuple(PeerEntry.of(peer) for peer in found))

    def close(self) -> None:
        for client in self._clients.values():
            client.close()
        self._clients.clear()


class Observer:
    """Samples the running robots' neighbour lists every `period` seconds of `clock` (in a
    thread with the real clock; as virtual time passes with a `VirtualClock`)."""

    def __init__(
        self,
        probe: Probe,
        truth: TruthLog,
        period: float = 0.25,
        clock: Clock = REAL,
    ) -> None:
        if period <= 0:
            raise ValueError(f"period must be positive, not {period}")
        self.probe = probe
        self.truth = truth
        self.period = period
        self._clock = clock
        self._samples: list[Sample] = []
        self._lock = threading.Lock()
        self._cancel: Callable[[], None] | None = None

    def start(self) -> Observer:
        self._cancel = self._clock.every(self.period, self.sample)
        return self

    def stop(self) -> list[Sample]:
        """Stop sampling (idempotent); the samples taken."""
        if self._cancel is not None:
            self._cancel()
            self._cancel = None
        self.probe.close()
        return self.samples

    @property
    def samples(self) -> list[Sample]:
        with self._lock:
            return list(self._samples)

    def sample(self) -> None:
        """Take one sample now."""
        t = self._clock.time()
        running = natural_order(list(self.truth.now().running))
        views = self.probe.neighbours(running)
        seen = {a: v.reachable for a, v in views.items() if v.error is None}
        indicators = {
            a: {e.robot_id: e.indicator for e in v.entries if e.indicator is not None}
            for a, v in views.items()
            if v.error is None
        }
        with self._lock:
            self._samples.append(Sample(t, seen, indicators))
