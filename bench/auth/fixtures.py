"""What every measure of the auth bench shares: the key, the seal as the measured sdfr makes
it, a robot's services, the two fleets (open, keyed)."""

from __future__ import annotations

import inspect
from collections.abc import Iterator
from pathlib import Path

from sdfr import wire
from sdfr.protocol import auth
from sdfr.protocol.auth import Keyring, Sealed
from sdfr.records.model import Service
from sdfr.wire import Reject

ROOT = Path(__file__).resolve().parents[2]
KEY = bytes(range(32))
COUNTER = 123_456  # six digits: a robot's counter after about a day of a small fleet
FIVE_MINUTES_S = 300.0
STARTUP_S = 30.0
#: Seals that name their recipient and the sender's address (seals v2, f0bc644); before,
#: `auth.seal(data, key, counter)` and `auth.check(data, keyring)` took nothing else.
BOUND_SEALS = "to" in inspect.signature(auth.seal).parameters
#: Pings and beacons carry 64-bit random nonces since f0bc644 (before: a 30-bit random start,
#: counting up): a typical sequence number of each, for the datagram sizes.
SEQ = 11_400_714_819_323_198_485 if wire.MAX_SEQ > 2**53 else 1_034_567_890


def seal(data: bytes, counter: int, *, to: str | None = None, sender: str = "") -> bytes:
    """`auth.seal` with KEY, bound to recipient and sender where the seals say them."""
    if BOUND_SEALS:
        return auth.seal(data, KEY, counter, to=to, sender=sender)
    return auth.seal(data, KEY, counter)


def check(data: bytes, ring: Keyring, *, me: str = "", src: str = "") -> Sealed | Reject | None:
    if BOUND_SEALS:
        return auth.check(data, ring, me=me, src=src)
    return auth.check(data, ring)


def services(robot: str, n: int) -> list[Service]:
    return [
        Service(
            id=f"{robot}-{i:03d}",
            name=f"{robot} service {i}",
            type=f"sensor.kind{i % 7}",
            url=f"http://{robot}.local:9000/s{i}",
            attributes={"fps": 30, "frame": f"{robot}/base_link"},
        )
        for i in range(n)
    ]


def rings() -> Iterator[tuple[str, Keyring]]:
    yield "open", auth.OPEN
    yield "keyed", Keyring.of([KEY])
