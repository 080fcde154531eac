"""The discovery layer's note of datagrams sealed with keys it does not hold
(sdfr.daemon.unknownkeys), in virtual time."""

from __future__ import annotations

import tracemalloc

import pytest

from sdfr.daemon import unknownkeys
from sdfr.daemon.unknownkeys import KEPT, LOG_EVERY, UnknownKeys
from tests.support.memory import grown

WINDOW = 30.0  # the default miss window: 3 beacons of 10 s


def test_the_first_datagram_of_a_key_id_is_said_then_once_a_minute() -> None:
    seen = UnknownKeys(WINDOW)
    told = []
    for t in range(0, 130, 10):
        said = seen.saw("0badc0de", "10.7.0.3", t)
        if said is not None:
            told.append((said.count, said.address))
    # At 0 s (the first), 60 s and 120 s: a robot beaconing every 10 s fills no log.
    assert told == [(1, "10.7.0.3"), (7, "10.7.0.3"), (13, "10.7.0.3")]
    assert LOG_EVERY == 60.0
    # Another key id is said at once, whatever the first one's.
    assert seen.saw("deadbeef", "10.7.0.4", 121.0) is not None


def test_it_lasts_while_they_come_and_clears_a_window_after_the_last() -> None:
    seen = UnknownKeys(WINDOW)
    for t in (0.0, 10.0, 20.0):
        seen.saw("0badc0de", "10.7.0.3", t)
    seen.saw("0badc0de", "10.7.0.9", 25.0)  # (moved, or another robot left out alike)
    [one] = seen.recent(25.0 + WINDOW)
    assert (one.kid, one.address, one.count) == ("0badc0de", "10.7.0.9", 4)
    assert (one.first_seen, one.last_seen) == (0.0, 25.0)
    assert seen.kids(25.0 + WINDOW) == ("0badc0de",)
    assert seen.recent(25.0 + WINDOW + 0.1) == [] and seen.kids(60.0) == ()
    # Back later: a new sighting, said again, counted from 1.
    again = seen.saw("0badc0de", "10.7.0.3", 100.0)
    assert again is not None and (again.count, again.first_seen) == (1, 100.0)


def test_the_latest_comes_first() -> None:
    seen = UnknownKeys(WINDOW)
    seen.saw("aaaaaaaa", "10.7.0.3", 1.0)
    seen.saw("bbbbbbbb", "10.7.0.4", 2.0)
    seen.saw("aaaaaaaa", "10.7.0.3", 3.0)
    assert [s.kid for s in seen.recent(3.0)] == ["aaaaaaaa", "bbbbbbbb"]


def test_a_flood_of_made_up_key_ids_costs_a_bounded_table() -> None:
    """Key ids in refused seals are not authenticated: an outsider can write any."""
    seen = UnknownKeys(WINDOW)
    seen.saw("0badc0de", "10.7.0.3", 0.0)
    tracemalloc.start()
    try:
        for n in range(20_000):
            seen.saw(f"{n:08x}", "10.7.0.66", 1.0 + n * 1e-6)
            if n == 1_000:
                before = tracemalloc.take_snapshot()
        after = tracemalloc.take_snapshot()
    finally:
        tracemalloc.stop()
    more = grown(before, after, [unknownkeys.__file__, __file__])
    assert more < 4096, f"{more} bytes more after 19,000 more key ids"
    now = 1.0 + 20_000 * 1e-6
    kept = seen.recent(now)
    assert len(kept) == KEPT == 16
    assert [s.kid for s in kept][:2] == [f"{19_999:08x}", f"{19_998:08x}"]  # the latest kept
    # The real one, heard longest ago, gave way; it comes back with its next datagram.
    assert "0badc0de" not in seen.kids(now)
    assert seen.saw("0badc0de", "10.7.0.3", now) is not None
    assert "0badc0de" in seen.kids(now)


def test_a_window_must_be_positive() -> None:
    with pytest.raises(ValueError, match="window"):
        UnknownKeys(0.0)
