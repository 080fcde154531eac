"""Token buckets, on the caller's clock: the protocol core's bounds on work and replies."""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass


@dataclass(slots=True)
class TokenBucket:
    """`rate` tokens a second, at most `burst` saved up; starts full."""

    rate: float
    burst: float
    tokens: float = -1.0
    stamp: float = 0.0

    def level(self, now: float) -> float:
        """The tokens saved up by `now` (nothing spent)."""
        if self.tokens < 0:
            return self.burst
        if now > self.stamp:
            return min(self.burst, self.tokens + (now - self.stamp) * self.rate)
        return self.tokens

    def take(self, now: float, n: float = 1.0) -> bool:
        """Spend `n` tokens if there are that many; False (and nothing spent) otherwise."""
        self.tokens, self.stamp = self.level(now), max(now, self.stamp)
        if self.tokens < n:
            return False
        self.tokens -= n
        return True

    def wait(self, now: float, n: float = 1.0) -> float:
        """Seconds from `now` until `n` tokens are saved up (0: they are)."""
        return max(0.0, (n - self.level(now)) / self.rate)


class KeyedBuckets:
    """One bucket per key (a source address), at most `max_keys` of them: the least recently
    used is forgotten first, which at worst gives that key a full bucket again."""

    def __init__(self, rate: float, burst: float, max_keys: int) -> None:
        self.rate = rate
        self.burst = burst
        self.max_keys = max_keys
        self._buckets: OrderedDict[str, TokenBucket] = OrderedDict()

    def take(self, key: str, now: float, n: float = 1.0) -> bool:
        bucket = self._buckets.get(key)
        if bucket is None:
            if len(self._buckets) >= self.max_keys:
                self._buckets.popitem(last=False)
            bucket = self._buckets[key] = TokenBucket(self.rate, self.burst)
        else:
            self._buckets.move_to_end(key)
        return bucket.take(now, n)

    def __len__(self) -> int:
        return len(self._buckets)


class ByteCredit:
    """Bytes received from each key (a source address) not yet spent on answers to it: what
    may be sent back there without amplifying.  At most `cap` saved per key and `max_keys`
    keys; the least recently used is forgotten first, which at worst leaves it no credit."""

    def __init__(self, cap: int, max_keys: int) -> None:
        self.cap = cap
        self.max_keys = max_keys
        self._credit: OrderedDict[str, int] = OrderedDict()

    def earn(self, key: str, n: int) -> None:
        credit = self._credit.pop(key, 0)
        if len(self._credit) >= self.max_keys:
            self._credit.popitem(last=False)
        self._credit[key] = min(self.cap, credit + n)

    def spend(self, key: str, n: int) -> bool:
        """Spend `n` bytes of `key`'s credit if it has that many; False (nothing spent) if not."""
        credit = self._credit.get(key, 0)
        if credit < n:
            return False
        self._credit[key] = credit - n
        return True

    def __len__(self) -> int:
        return len(self._credit)
