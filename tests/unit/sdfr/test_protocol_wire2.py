"""Wire version 2 in virtual time: compact forms and who gets them, beacons that ping the
fleet, changes told of once announced, bursts gathered within the gap, catch-up deltas, and a
fleet that mixes in a robot of wire version 1."""

from __future__ import annotations

import itertools
import random
import statistics

from sdfr import wire
from sdfr.protocol import auth
from sdfr.protocol.auth import Keyring
from sdfr.protocol.config import REPAIR_MEMORY, answers_beacon
from sdfr.records.model import Service
from sdfr.testing.simnet import BEACON, SimNet, kind_of, sent, services

#: The product's ping: one per beacon period, so beacons are the pings.
PRODUCT = {"beacon_interval": BEACON, "ping_interval": BEACON}


def product_fleet(net: SimNet, n: int, n_services: int = 20, **cfg: object) -> list[str]:
    names = [f"r{i}" for i in range(1, n + 1)]
    for name in names:
        net.add(name, services=services(name, n_services), **{**PRODUCT, **cfg})
    return names


def compact(data: bytes) -> bool:
    msg = wire.decode(data)
    return not isinstance(msg, wire.Reject) and msg.origin is not None and b"\r\nX-SDFR: " in data


def test_a_fleet_of_wire_2_robots_speaks_compact_and_pings_by_beacon() -> None:
    net = SimNet(seed=201)
    names = product_fleet(net, 4)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(3 * BEACON)
    t0 = net.now
    window = {n: len(net.nodes["r1"].core.peers[n].pings) for n in names[1:]}
    net.run_for(10 * BEACON)
    for name in names:
        out = [d for t, d, _ in net.nodes[name].sent if t >= t0]
        assert out and all(compact(d) for d in out)
        assert sent(net, name, "ping", since=t0) == []  # no unicast ping at all
        beacons = [wire.decode(d) for _, d, _ in sent(net, name, "alive", since=t0)]
        assert all(isinstance(b, wire.Alive) and b.seq is not None for b in beacons)
        # Each robot answers each other's beacons: one reply per peer per beacon.
        replies = sent(net, name, "reply", since=t0)
        assert 3 * 10 * 0.9 <= len(replies) <= 3 * 11 + 1
    r1 = net.nodes["r1"].core
    for peer in names[1:]:
        p = r1.peers[peer]
        assert 9 <= len(p.pings) - window[peer] <= 12  # a round trip a beacon
        assert p.indicator == 1.0
        assert p.rtt is not None and 0.002 <= p.rtt <= 0.008  # simnet: 1-4 ms each way


def test_beacon_pings_tell_a_silent_death_and_the_loss_of_round_trips() -> None:
    net = SimNet(seed=202)
    names = product_fleet(net, 3, ping_window=1000)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(5 * BEACON)
    before = net.nodes["r1"].core.peers["r3"].indicator
    net.kill("r3")
    took = net.wait_until(lambda: not net.sees("r1", "r3") and not net.sees("r2", "r3"), 3.5)
    assert took <= 3 * BEACON + 0.1
    after = net.nodes["r1"].core.peers["r3"].indicator
    assert before == 1.0 and after is not None and after < before
    # 30 % loss each way between r1 and r2: a round trip gets through 0.7 x 0.7 = 0.49 of
    # the time, which is what the indicator tells.
    net.pair_loss[("r1", "r2")] = net.pair_loss[("r2", "r1")] = 0.3
    p = net.nodes["r1"].core.peers["r2"]
    p.pings.clear()
    net.run_for(400 * BEACON)
    assert p.indicator is not None and abs(p.indicator - 0.49) <= 0.08, p.indicator
    assert len(p.pings) >= 360


def test_a_change_is_told_of_only_once_it_is_announced() -> None:
    """While a change waits for its announcement, beacons and replies still name the set
    announced: nobody fetches a set that is about to come by multicast."""
    net = SimNet(seed=203)
    names = product_fleet(net, 4, update_gap=0.4)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(2 * BEACON)
    t0 = net.now
    for v in range(2, 40):
        net.set_services("r1", v, services("r1", 20 + v % 3))
        net.run_for(0.07 * (1 + v % 4))
    net.wait_until(lambda: net.all_see_all(names), timeout=1.0)
    for name in names:
        assert sent(net, name, "fetch", since=t0) == []
        assert sent(net, name, "update", since=t0) == []  # no whole set: deltas only
    # Every datagram r1 sent names a version it announced by then (a delta's own version).
    told: set[int] = {1}
    for _, d, _ in net.nodes["r1"].sent:
        msg = wire.decode(d)
        assert not isinstance(msg, wire.Reject) and msg.origin is not None
        if isinstance(msg, wire.Update):
            told.add(msg.origin.version)
        assert msg.origin.version in told


def test_changes_go_out_at_once_while_saved_up_then_one_a_gap() -> None:
    """Announcements are a token bucket (`update_burst` saved up, one back each `update_gap`):
    five changes 50 ms apart: the first three go out at once, the bucket is then empty, and
    the last two gather into one announcement when the next is saved up."""
    net = SimNet(seed=204)
    names = product_fleet(net, 3, update_gap=0.25, update_burst=3)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(2 * BEACON)
    r1 = net.nodes["r1"]
    t0 = net.now
    for v in range(2, 7):
        net.set_services("r1", v, services("r1", 19 + v))
        net.run_for(0.05)
    net.wait_until(lambda: net.all_see_all(names), timeout=0.5)
    deltas = [(t, wire.decode(d)) for t, d, _ in sent(net, "r1", "delta", since=t0)]
    announced = [(t - t0, m.origin.version) for t, m in deltas if isinstance(m, wire.Update)]
    assert [v for _, v in announced] == [2, 3, 4, 6], announced
    for i, (t, _) in enumerate(announced[:3]):  # each at once
        assert abs(t - 0.05 * i) <= r1.core.config.update_coalesce + 1e-9, announced
    # 3 tokens, 3 spent by t0 + 0.1 s, 0.4 back by then (4 a second): the 4th at t0 + 0.25 s
    assert abs(announced[3][0] - 0.25) <= 1e-6, announced
    # Seen everywhere within the product's 500 ms of each change.
    assert net.now - t0 <= 0.5


def test_at_the_paper_s_churn_changes_go_out_at_once() -> None:
    """The paper's churn on one robot (a change every 1.25 s on average, at random): with the
    product's bucket at least 98 % of changes are announced when they are made and 99 % within
    20 ms, none later than a gap. (With the gap alone, `update_burst=1`: 87-91 % at once,
    the 99th percentile 0.20-0.25 s, seeds 0-4.)"""
    net = SimNet(seed=206)
    names = product_fleet(net, 3)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(2 * BEACON)
    rng = random.Random(7)
    made: dict[int, float] = {}
    t0 = net.now
    for v in range(2, 200):
        made[v] = net.now
        net.set_services("r1", v, services("r1", 20 + v % 5))
        net.run_for(rng.uniform(0.0, 2.5))
    deltas = [(t, wire.decode(d)) for t, d, _ in sent(net, "r1", "delta", since=t0)]
    told = {m.origin.version: t for t, m in deltas if isinstance(m, wire.Update)}
    # A change gathered into a later one's announcement waited for it.
    waits = [min(t for w, t in told.items() if w >= v) - at for v, at in made.items()]
    waits.sort()
    at_once = sum(w <= 1e-9 for w in waits) / len(waits)
    p99 = waits[int(0.99 * len(waits))]
    assert at_once >= 0.98 and p99 <= 0.02, (at_once, p99, waits[-5:])
    assert waits[-1] <= net.nodes["r1"].core.config.update_gap + 1e-9, waits[-1]


def test_a_robot_too_far_behind_gets_the_whole_set() -> None:
    net = SimNet(seed=205)
    names = product_fleet(net, 3, delta_history=2)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(2 * BEACON)
    net.filter = lambda src, dst, data: not (src == "r1" and dst == "r2")
    for v in range(2, 6):
        net.set_services("r1", v, services("r1", 20 + v))
        net.run_for(0.3)
    net.filter = None
    t0 = net.now
    net.wait_until(lambda: net.all_see_all(names), timeout=2 * BEACON)
    asks = [wire.decode(d) for _, d, _ in sent(net, "r2", "fetch", since=t0)]
    assert asks and all(isinstance(a, wire.Discovery) and a.have == 1 for a in asks)
    # r1 keeps only its last 2 sets (4 and 5): version 1 is gone, so the whole set it is.
    r2 = net.nodes["r2"].addr
    to_r2 = [kind_of(d) for t, d, dst in net.nodes["r1"].sent if t >= t0 and dst == r2]
    assert "update" in to_r2 and "delta" not in to_r2


def test_a_fleet_mixing_in_a_wire_1_robot_speaks_it_full_forms() -> None:
    """A robot of wire version 1 rejects compact datagrams as not SDfR (`old` stands for one:
    it sends only full forms, and the medium drops every compact datagram to it as its
    decoder would).  The others write to it, and to the group while it is in range, in full
    forms, and ping it by unicast; among themselves unicasts stay compact.  Once it has left,
    the group hears compact forms again."""
    net = SimNet(seed=206)
    net.filter = lambda src, dst, data: not (dst == "old" and compact(data))
    names = product_fleet(net, 3)
    net.add("old", services=services("old", 10), wire_compact=False, **PRODUCT)
    everyone = [*names, "old"]
    net.wait_until(lambda: net.all_see_all(everyone), timeout=3.0)
    net.run_for(2 * BEACON)
    t0 = net.now
    for v in range(2, 6):
        net.set_services("r1", v, services("r1", 20 + v))
        net.set_services("old", v, services("old", 10 + v))
        net.run_for(0.6)
    net.wait_until(lambda: net.all_see_all(everyone), timeout=1.0)
    net.run_for(3 * BEACON)
    old = net.nodes["old"].addr
    for name in names:
        out = [(d, dst) for t, d, dst in net.nodes[name].sent if t >= t0]
        assert all(not compact(d) for d, dst in out if dst is None or dst == old)
        among = [d for d, dst in out if dst is not None and dst != old]
        assert among and all(compact(d) for d in among)
        assert sent(net, name, "ping", since=t0)  # old is pinged by unicast
        assert net.nodes[name].core.peers["old"].indicator == 1.0
    assert all(not compact(d) for t, d, _ in net.nodes["old"].sent)
    net.stop("old")
    net.run_for(BEACON)
    t1 = net.now
    net.run_for(2 * BEACON)
    group = [d for t, d, dst in net.nodes["r1"].sent if t >= t1 and dst is None]
    assert group and all(compact(d) for d in group)


def test_an_unsigned_compact_search_is_no_plain_ssdp_search_in_a_keyed_fleet() -> None:
    ring = Keyring.of([bytes(range(32))])
    net = SimNet(seed=207)
    product_fleet(net, 2, keyring=ring)
    net.run_for(2 * BEACON)
    core = net.nodes["r1"].core
    forged = wire.Origin(1, "r9", 5, 1, "0" * 16, wire.WIRE_COMPACT)
    search = wire.encode(
        wire.Discovery(forged, "uuid:r1", 0, want=wire.WANT_ALL, multicast=False), compact=True
    )
    was = core.counters.rejects["unsigned"]
    net.inject("r1", search, ("10.1.0.66", 1900))
    assert core.counters.rejects["unsigned"] == was + 1
    assert "r9" not in core.peers
    # Sealed, the compact forms go through as any other.
    assert auth.check(net.nodes["r2"].sent[-1][1], ring) is not None


def test_a_churning_fleet_stays_within_500ms_and_never_fetches() -> None:
    """The paper's load in miniature: every robot unpublishes a service every 0-5 s (fresh
    ids), publishing another in its place; every change is listed on every peer within the
    product's 500 ms, by multicast deltas alone."""
    net = SimNet(seed=208)
    names = product_fleet(net, 4, n_services=30)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(2 * BEACON)
    t0 = net.now
    rng = net.rng
    version = {n: 1 for n in names}
    current: dict[str, list[Service]] = {n: list(net.nodes[n].core.services) for n in names}
    lags: list[float] = []
    for step in range(120):
        name = rng.choice(names)
        svcs = current[name]
        svcs.pop(rng.randrange(len(svcs)))
        svcs.append(Service(f"{name}-x{step}", f"publisher {step}", "bench.kind"))
        version[name] += 1
        net.set_services(name, version[name], list(svcs))
        target = sorted(svcs, key=lambda s: s.id)
        lags.append(
            net.wait_until(
                lambda n=name, want=target: all(
                    sorted(net.nodes[x].core.peers[n].services, key=lambda s: s.id) == want
                    for x in names
                    if x != n
                ),
                timeout=0.5,
            )
        )
        net.run_for(rng.uniform(0.0, 1.25))
    assert max(lags) <= 0.5 and statistics.median(lags) < 0.1
    for name in names:
        assert sent(net, name, "fetch", since=t0) == []
        # Nothing lost, nothing to repair: every delta is its own step alone.
        deltas = [wire.decode(d) for _, d, _ in sent(net, name, "delta", since=t0)]
        assert deltas and all(isinstance(m, wire.Update) and not m.steps for m in deltas)


def test_the_listed_rtt_follows_a_link_that_slows_while_every_round_trip_succeeds() -> None:
    net = SimNet(seed=209)
    names = product_fleet(net, 3, n_services=2)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(3 * BEACON)
    r1 = net.nodes["r1"].core
    r1.take_dirty()
    net.run_for(10 * BEACON)
    # Steady 1-4 ms round trips: the indicator stays 1.0, the RTT barely moves: no writes.
    assert r1.peers["r2"].indicator == 1.0 and r1.take_dirty() == []
    net.delay = (0.05, 0.05)  # every link now 50 ms each way: no round trip is lost
    net.run_for(20 * BEACON)
    listed = {v.robot_id: v for v in r1.take_dirty()}
    assert listed["r2"].indicator == 1.0
    assert listed["r2"].rtt_ms is not None and 80 <= listed["r2"].rtt_ms <= 100
    net.run_for(10 * BEACON)  # settled: at most a write or two as it converges on 100 ms
    assert len([v for v in r1.take_dirty() if v.robot_id == "r2"]) <= 1


def test_after_a_catch_up_deltas_carry_the_step_before_and_a_miss_costs_no_fetch() -> None:
    """On a link that loses datagrams: once a peer had to ask for a catch-up, the sender's
    deltas also carry the step before their own (for REPAIR_MEMORY), so that a robot that
    missed one delta applies the next without asking; a quiet spell ends it."""
    net = SimNet(seed=209)
    names = product_fleet(net, 3, n_services=30)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(2 * BEACON)
    current = list(net.nodes["r1"].core.services)
    version = 1

    def change(*, lost_to_r2: bool = False) -> None:
        """One change of r1's set, r2 losing its delta when told; right after r1's beacon,
        so that no beacon tells r2 of it before the next change."""
        nonlocal version
        beacons = len(sent(net, "r1", "alive"))
        net.wait_until(lambda: len(sent(net, "r1", "alive")) > beacons, timeout=2 * BEACON)
        current.pop(0)
        current.append(Service(f"r1-x{version}", f"fresh {version}", "bench.kind"))
        version += 1
        if lost_to_r2:
            net.filter = lambda src, dst, data: (
                not (src == "r1" and dst == "r2" and kind_of(data) == "delta")
            )
        net.set_services("r1", version, list(current))
        net.run_for(0.05)
        net.filter = None

    def listed(name: str) -> bool:
        mine = sorted(current, key=lambda s: s.id)
        return sorted(net.nodes[name].core.peers["r1"].services, key=lambda s: s.id) == mine

    def steps_of(since: float) -> list[int]:
        out = []
        for _, data, dst in sent(net, "r1", "delta", since=since):
            msg = wire.decode(data)
            assert isinstance(msg, wire.Update) and dst is None
            out.append(len(msg.steps))
        return out

    # No loss yet: single-step deltas.
    t0 = net.now
    change()
    net.wait_until(lambda: listed("r2") and listed("r3"), timeout=0.5)
    assert steps_of(t0) == [0]
    # r2 misses one: it asks r1 for what changed since the set it holds.
    t1 = net.now
    change(lost_to_r2=True)
    net.wait_until(lambda: listed("r2"), timeout=2 * BEACON)
    asks = [wire.decode(d) for _, d, _ in sent(net, "r2", "fetch", since=t1)]
    assert asks and all(isinstance(a, wire.Discovery) and a.have == 2 for a in asks)
    # From now on each delta carries the step before it: r2 misses one, asks nothing, and
    # lists the set of the next delta within 500 ms of that change, as r3 does.
    t2 = net.now
    change(lost_to_r2=True)
    net.run_for(0.25)
    assert not listed("r2") and listed("r3")
    t3 = net.now
    net.set_services("r1", version + 1, list(current))  # the same services, a new version
    version += 1
    for name in ("r2", "r3"):
        peer = net.nodes[name].core.peers["r1"]
        net.wait_until(lambda p=peer: p.held is not None and p.held[1] == version, 0.5)
        assert listed(name)
    assert sent(net, "r2", "fetch", since=t2) == []
    assert steps_of(t2) == [1, 1]
    # The step costs bytes on every delta: it goes once nobody asked for a while.
    net.run_for(REPAIR_MEMORY)
    t4 = net.now
    change()
    net.wait_until(lambda: listed("r2") and listed("r3"), timeout=0.5)
    assert steps_of(t3) == [1, 0] and steps_of(t4) == [0]


def test_in_a_fleet_larger_than_beacon_answers_the_peers_take_turns_answering() -> None:
    """A beacon asks at most about `beacon_answers` peers to answer: what a robot sends for
    the indicator stays bounded as the fleet grows, each pair still measured (every
    ceil(peers / beacon_answers) beacons), silent deaths seen as soon, losses still told."""
    net = SimNet(seed=210)
    names = product_fleet(net, 7, n_services=5, beacon_answers=2, ping_window=1000)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(3 * BEACON)
    t0 = net.now
    window = {n: len(net.nodes["r1"].core.peers[n].pings) for n in names[1:]}
    net.run_for(60 * BEACON)
    for name in names:
        beacons = [wire.decode(d) for _, d, _ in sent(net, name, "alive", since=t0)]
        assert beacons and all(isinstance(b, wire.Alive) and b.turns == 3 for b in beacons)
        # The turns go round by sequence number (a turn no peer has is passed over).
        turns = [b.seq % 3 for b in beacons if isinstance(b, wire.Alive) and b.seq is not None]
        assert all(a != b for a, b in itertools.pairwise(turns))
        # 6 peers' beacons, each answered by a third of them: about 2 replies a period, not 6.
        replies = len(sent(net, name, "reply", since=t0))
        assert 60 * 6 / 3 * 0.6 <= replies <= 60 * 6 / 3 * 1.5, replies
    r1 = net.nodes["r1"].core
    for peer in names[1:]:
        p = r1.peers[peer]
        # Measured every third beacon, and never counted lost for a beacon not its turn.
        assert 60 / 3 * 0.8 <= len(p.pings) - window[peer] <= 60 / 3 * 1.2 + 1
        assert p.indicator == 1.0 and p.rtt is not None
    net.kill("r7")
    took = net.wait_until(lambda: not any(net.sees(n, "r7") for n in names[:-1]), 3.5)
    assert took <= 3 * BEACON + 0.1
    # 30 % loss each way between r1 and r2: the indicator still tells 0.49.
    net.pair_loss[("r1", "r2")] = net.pair_loss[("r2", "r1")] = 0.3
    p = r1.peers["r2"]
    p.pings.clear()
    net.run_for(900 * BEACON)
    assert p.indicator is not None and abs(p.indicator - 0.49) <= 0.08, p.indicator
    # A fleet within beacon_answers: every peer answers every beacon, no turns said.
    small = SimNet(seed=211)
    few = product_fleet(small, 3, n_services=5, beacon_answers=2)
    small.wait_until(lambda: small.all_see_all(few), timeout=2.0)
    small.run_for(3 * BEACON)
    for _, data, _ in sent(small, "r1", "alive"):
        beacon = wire.decode(data)
        assert isinstance(beacon, wire.Alive) and beacon.turns == 1


def test_each_robot_answers_one_turn_of_a_beacons_turns() -> None:
    ids = [f"robot-{i:03d}" for i in range(200)]
    for turns in (1, 2, 5, 13):
        for rid in ids[:50]:
            assert sum(answers_beacon(rid, seq, turns) for seq in range(1000, 1000 + turns)) == 1
        # Turns are about even: each takes a fair share of 200 robots.
        shares = [sum(answers_beacon(rid, t, turns) for rid in ids) for t in range(turns)]
        assert min(shares) >= 200 / turns * 0.5
