"""Datagrams sealed with keys this robot does not hold: which key ids, from where, lately.

A robot left out of a key rotation goes on sealing with a key the others removed, and every
datagram of it is dropped as "unknown-key": it is cut off. The discovery layer notes each such
datagram here (the key id its seal names, its source address) and says so: a warning in the
log at most once a LOG_EVERY per key id, a /health warning while any came within the window
(the miss window: as long as a robot that is heard would stay listed), and the list in
`sdfr keys list`. No I/O, no clock: every call takes `now`.

The key id of a refused seal is not authenticated (anybody can write any 8 hex digits), so
what a flood of made-up ids costs is bounded: KEPT key ids, the one heard longest ago giving
way to a new one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: Key ids remembered at most.
KEPT = 16
#: Seconds between two warnings in the log about one key id.
LOG_EVERY = 60.0


@dataclass(slots=True)
class Sighting:
    """Datagrams sealed with one unknown key id."""

    kid: str
    #: The source address of the latest.
    address: str
    count: int
    first_seen: float
    last_seen: float
    #: When the log last said so (-inf: never).
    logged_at: float = -math.inf


class UnknownKeys:
    """The unknown key ids heard within the last `window` seconds, KEPT at most."""

    def __init__(self, window: float) -> None:
        if window <= 0:
            raise ValueError(f"window must be positive, not {window}")
        self.window = window
        self._seen: dict[str, Sighting] = {}

    def saw(self, kid: str, address: str, now: float) -> Sighting | None:
        """A datagram sealed with key `kid` came from `address` and was refused; the sighting
        when the log should say so now (the first of its key id, then once a LOG_EVERY)."""
        seen = self._seen.get(kid)
        if seen is None or now - seen.last_seen > self.window:
            self._seen.pop(kid, None)
            if len(self._seen) >= KEPT:
                oldest = min(self._seen.values(), key=lambda s: s.last_seen)
                del self._seen[oldest.kid]
            seen = self._seen[kid] = Sighting(kid, address, 0, now, now)
        seen.address = address
        seen.count += 1
        seen.last_seen = now
        if now - seen.logged_at < LOG_EVERY:
            return None
        seen.logged_at = now
        return seen

    def recent(self, now: float) -> list[Sighting]:
        """The key ids heard within the window, the latest first; older ones are forgotten."""
        for kid in [k for k, s in self._seen.items() if now - s.last_seen > self.window]:
            del self._seen[kid]
        return sorted(self._seen.values(), key=lambda s: s.last_seen, reverse=True)

    def kids(self, now: float) -> tuple[str, ...]:
        """The key ids of `recent`, sorted: what changes the status when it changes."""
        return tuple(sorted(s.kid for s in self.recent(now)))
