"""What an outsider who fights a robot over ARP for as long as it likes costs the robot: the
address machine's memory stays bounded, and it never runs out of addresses to try."""

from __future__ import annotations

import random
import subprocess
import sys
import tracemalloc

from sdfr.protocol import addressing
from sdfr.protocol.addressing import AddrConfig, Addressing, Arp, State
from tests.support.memory import grown

ROBOT = "02:00:00:00:12:34"
#: Lower than any robot's MAC: it keeps every address it claims, the robot moves each time.
OUTSIDER = "00:00:00:00:00:01"


def _settle(m: Addressing, now: float) -> float:
    """Run the machine's timers until it probes (or holds) an address; the time then."""
    for _ in range(20):
        deadline = m.next_deadline()
        if deadline is None:
            return now
        now = max(now, deadline)
        m.handle_timer(now)
        m.arp_to_send()
        m.actions()
        if m.state is State.PROBING:
            return now
    raise AssertionError(f"the machine never probes again (state {m.state})")


def flood(m: Addressing, conflicts: int, now: float) -> float:
    """`conflicts` conflicts, half while the robot probes (the outsider answers the probe),
    half after it took the address (the outsider claims it with its lower MAC)."""
    for i in range(conflicts):
        now = _settle(m, now)
        if i % 2:  # let it take the address, then claim it
            while m.state is not State.BOUND:
                now = m.next_deadline() or now
                m.handle_timer(now)
            m.arp_to_send()
            m.actions()
        assert m.ip is not None
        ip = m.ip
        m.handle_arp(Arp(2, OUTSIDER, ip, ip), now)
        assert m.ip != ip  # it gave the address up
    return now


def test_a_flood_of_conflicts_keeps_memory_bounded_and_counts_them_all() -> None:
    m = Addressing(AddrConfig(fleet=7, mac=ROBOT), random.Random(1))
    m.start(0.0)
    tracemalloc.start()
    try:
        now = flood(m, 1_000, 0.0)
        before = tracemalloc.take_snapshot()
        flood(m, 10_000, now)
        after = tracemalloc.take_snapshot()
    finally:
        tracemalloc.stop()
    more = grown(before, after, [addressing.__file__, __file__])
    # Before the records, the lost addresses and the sequence's memory were bounded: 4 MB.
    assert more < 32 * 1024, f"{more} bytes more after 10,000 more conflicts"
    assert len(m.conflicts) <= 64
    assert m.conflicts_total == 11_000
    last = list(m.conflicts)[-1]
    assert last.other_mac == OUTSIDER and not last.kept  # the newest are the ones kept


# The whole candidate sequence of one MAC, and some more: every address of 10.7.0.0/16 whose
# octets are 1-254 once, then again from the start (the generator used to loop for ever here).
EXHAUST = """
import itertools
from sdfr.protocol.addressing import candidates
n = 254 * 254
seq = candidates(7, "02:00:00:00:12:34")
first = list(itertools.islice(seq, n))
again = list(itertools.islice(seq, 3))
assert len(set(first)) == n, len(set(first))
assert again == first[:3], (again, first[:3])
print("ok")
"""


def test_the_candidate_sequence_starts_over_instead_of_running_dry() -> None:
    try:
        done = subprocess.run(
            [sys.executable, "-c", EXHAUST], capture_output=True, text=True, timeout=60
        )
    except subprocess.TimeoutExpired:
        raise AssertionError("the 64,517th candidate never came: the sequence ran dry") from None
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr
