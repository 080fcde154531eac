"""A patient outsider: one who records everything the robots say, relays it between robots and
partitions, replays it after a robot restarts, and aims the robots' answers at a victim.

Each test is one finding of issue 25, in virtual time with the real protocol core; each failed
before the core believed only fresh answers (nonce pings), bound seals to their recipient and
sender address, and answered unproven addresses with no more bytes than they sent.
"""

from __future__ import annotations

from sdfr import wire
from sdfr.protocol import UNPROVEN_BYTES, Addr, Core, auth
from sdfr.protocol.auth import Keyring
from sdfr.records.model import Service, service_digest
from sdfr.testing.simnet import BEACON, SimNet, fleet, kind_of, services
from sdfr.wire import Alive, Discovery, Origin, Response, Update

KEY = bytes(range(32))
OUTSIDER: Addr = ("10.1.0.66", 1900)
VICTIM: Addr = ("10.1.0.77", 1900)


def keyed() -> Keyring:
    return Keyring.of([KEY])


def multicasts(net: SimNet, name: str, since: float = 0.0) -> list[bytes]:
    return [d for t, d, dst in net.nodes[name].sent if dst is None and t >= since]


def unicasts(net: SimNet, name: str, to: str) -> list[bytes]:
    addr = net.nodes[to].addr
    return [d for _, d, dst in net.nodes[name].sent if dst == addr]


def listed(net: SimNet, who: str, whom: str) -> bool:
    return whom in net.nodes[who].core.reachable()


def test_a_new_robot_does_not_list_a_dead_robot_from_its_replayed_multicasts() -> None:
    net = SimNet(seed=301)
    names = fleet(net, 3, n_services=5, keyring=keyed())
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(2 * BEACON)
    captured = multicasts(net, "r3")
    net.kill("r3")
    net.run_for(4 * BEACON)
    net.add("r4", services=services("r4", 2), keyring=keyed(), beacon_interval=BEACON,
            ping_interval=BEACON / 2)  # fmt: skip
    net.wait_until(lambda: listed(net, "r4", "r1") and listed(net, "r4", "r2"), 2.0)
    seen = False
    for data in captured:
        net.inject("r4", data, OUTSIDER)  # from the outsider's address ...
        net.inject("r4", data, net.nodes["r3"].addr)  # ... and forged from r3's own
        net.run_for(0.2)
        seen = seen or listed(net, "r4", "r3")
    net.run_for(2 * BEACON)
    assert not seen and not listed(net, "r4", "r3")
    core = net.nodes["r4"].core
    r3 = core.peers.get("r3")
    assert r3 is None or not r3.proven
    assert all(v.robot_id != "r3" for v in core.take_dirty())  # nor saved to its history
    assert core.counters.rejects["relayed"] >= len(captured)  # the ones from elsewhere
    assert core.counters.rejects["unproven"] >= 1  # the others: challenged, never answered


def test_after_a_restart_a_dead_robot_is_not_kept_listed_by_its_replays() -> None:
    net = SimNet(seed=302)
    names = fleet(net, 3, n_services=5, keyring=keyed())
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(2 * BEACON)
    history = net.nodes["r1"].core.take_dirty()
    for v in history:  # what r1's store holds: every peer it proved, as last seen
        assert v.robot_id in ("r2", "r3")
    t_dead = net.now
    net.run_for(3 * BEACON)
    captured = multicasts(net, "r3", since=t_dead)  # never heard by the r1 to come
    net.kill("r3")
    net.restart("r1", boot_id=2, graceful=False, history=history)
    net.wait_until(lambda: listed(net, "r1", "r2"), 2.0)
    listed_at = []
    for data in captured:
        net.inject("r1", data, net.nodes["r3"].addr)
        net.run_for(0.3)
        if listed(net, "r1", "r3"):
            listed_at.append(net.now)
    assert listed_at == [], f"r3 listed at {listed_at}"
    assert net.nodes["r1"].core.peers["r3"].known  # still in the history map, as it was


def test_unicasts_captured_between_two_robots_are_worth_nothing_to_a_third() -> None:
    net = SimNet(seed=303)
    names = fleet(net, 3, n_services=5, keyring=keyed())
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(3 * BEACON)
    captured = unicasts(net, "r3", "r2")  # r3's replies, pings and parts for r2
    assert captured
    net.kill("r3")
    r1 = net.nodes["r1"].core
    was = r1.counters.rejects["not-for-me"]
    end = net.now + 6 * BEACON
    seen_late = False
    dead_after = r1.config.dead_after
    while net.now < end:
        for data in captured:
            net.inject("r1", data, net.nodes["r3"].addr)
        net.run_for(0.5)
        if listed(net, "r1", "r3") and net.now > end - 6 * BEACON + dead_after + 0.5:
            seen_late = True
    assert not seen_late and not listed(net, "r1", "r3")
    assert r1.counters.rejects["not-for-me"] - was >= len(captured)


def test_a_relay_does_not_move_a_robot_to_the_relays_address() -> None:
    """r1 and r2 cannot hear each other; an outsider relays r2's datagrams to r1 from its own
    address (and r1's back to r2 as from r1's): a keyed r1 must not list r2 at the outsider.
    (An open fleet cannot tell such a relay, which answers its challenges, from a robot:
    docs/security.md says so.)"""
    net = SimNet(seed=304)
    fleet(net, 2, n_services=3, keyring=keyed())
    net.partition(["r1"], ["r2"])
    # Everything r2 sends reaches r1 as from the relay; what r1 sends to the group or the
    # relay reaches r2 as from r1 (the outsider spoofs r1 towards r2).
    relay = OUTSIDER

    r1, r2 = net.nodes["r1"], net.nodes["r2"]
    for _ in range(40):
        net.run_for(BEACON / 4)
        for data in [d for t, d, _ in r2.sent if t >= net.now - BEACON / 4]:
            net.inject("r1", data, relay)
        for data in [d for t, d, dst in r1.sent if t >= net.now - BEACON / 4 and
                     dst in (None, relay)]:  # fmt: skip
            net.inject("r2", data, r1.addr)
        if listed(net, "r1", "r2"):
            assert r1.core.peers["r2"].address != relay, "r2 listed at the relay"
    assert not listed(net, "r1", "r2")
    assert r1.core.counters.rejects["relayed"] > 0


def test_its_own_beacon_sent_back_raises_no_lasting_alarm() -> None:
    net = SimNet(seed=305)
    names = fleet(net, 2, n_services=3, keyring=keyed())
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    own = multicasts(net, "r1")[-1]
    net.inject("r1", own, OUTSIDER)
    core = net.nodes["r1"].core
    assert core.conflict is None and core.counters.rejects["relayed"] == 1
    # Open fleet: the same from elsewhere is challenged; nobody answers; no conflict.
    net2 = SimNet(seed=306)
    fleet(net2, 2, n_services=3)
    net2.wait_until(lambda: net2.all_see_all(["r1", "r2"]), timeout=2.0)
    own2 = multicasts(net2, "r1")[-1]
    net2.inject("r1", own2, OUTSIDER)
    net2.run_for(2 * BEACON)
    assert net2.nodes["r1"].core.conflict is None
    assert net2.nodes["r1"].core.counters.rejects["own-claim"] == 1


def test_a_second_daemon_is_reported_and_the_report_clears_once_it_is_gone() -> None:
    net = SimNet(seed=307)
    names = fleet(net, 2, n_services=3)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    twin = net.add("r2-twin", services=services("r2", 1), beacon_interval=BEACON,
                   ping_interval=BEACON / 2, start=False)  # fmt: skip
    from dataclasses import replace

    twin.core.config = replace(twin.core.config, robot_id="r2")
    twin.core.start(net.now)
    net.run_for(3 * BEACON)
    r2 = net.nodes["r2"].core
    assert r2.conflict is not None and r2.conflict.address == twin.addr[0]
    net.kill("r2-twin")
    net.run_for(r2.config.dead_after + 2 * BEACON)
    assert r2.conflict is None


def test_a_reused_boot_id_is_not_locked_out_and_a_lower_one_is_not_flipped_back() -> None:
    net = SimNet(seed=308)
    names = fleet(net, 3, n_services=5, keyring=keyed())
    net.restart("r3", boot_id=500, graceful=True)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(5 * BEACON)  # r3's counter climbs in boot 500
    old_life = multicasts(net, "r3")
    # Wiped and restarted with the same boot id: its counter starts again from 1.
    fresh = services("r3", 2, tag="again")
    net.restart("r3", boot_id=500, graceful=False, services=fresh, version=1)
    took = net.wait_until(
        lambda: (
            all(net.nodes[x].core.peers["r3"].services == tuple(fresh) for x in ("r1", "r2"))
            and net.all_see_all(names)
        ),
        timeout=2 * BEACON,
    )
    assert took <= 2 * BEACON
    # Re-imaged again with a lower boot id; the outsider replays its earlier life at once.
    newest = services("r3", 3, tag="new")
    net.restart("r3", boot_id=7, graceful=False, services=newest, version=1)
    net.wait_until(lambda: net.all_see_all(names), timeout=2 * BEACON)
    held = 0
    steps = 0
    for data in old_life * 2:
        net.inject("r1", data, net.nodes["r3"].addr)
        net.run_for(0.1)
        steps += 1
        held += net.nodes["r1"].core.peers["r3"].services == tuple(newest)
    assert held == steps  # its true set, all the time


def test_a_forged_answer_does_not_take_a_challenge_away() -> None:
    """Open fleet: a forged response with a re-imaged robot's id and any sequence number
    must not settle the challenge its real answer will settle."""
    net = SimNet(seed=309)
    names = fleet(net, 2, n_services=3)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    core = net.nodes["r1"].core
    r2 = net.nodes["r2"]
    seen_seqs = [
        m.seq
        for d in multicasts(net, "r1") + unicasts(net, "r1", "r2")
        if isinstance(m := wire.decode(d), Discovery | Alive) and m.seq is not None
    ]
    assert seen_seqs and all(s >= 2**32 for s in seen_seqs[-3:])  # 64-bit nonces
    net.restart("r2", boot_id=1, graceful=False, services=services("r2", 1, tag="x"), version=1)
    for seq in range(0, 4096):
        forged = Response(Origin(1, "r2", 1, 1, service_digest(()), 2), "uuid:r1", "", 0, seq)
        net.inject("r1", wire.encode(forged, compact=True), r2.addr)
    net.wait_until(lambda: net.all_see_all(names), timeout=2 * BEACON)
    assert core.peers["r2"].services == net.nodes["r2"].core.services


def test_open_fleet_bytes_to_a_forged_victim_never_exceed_what_it_sent() -> None:
    """Forged beacons claiming a victim's address, forged pings from it, fetches from it:
    each robot sends the victim no more bytes than it received from it."""
    net = SimNet(seed=310)
    names = fleet(net, 3, n_services=20)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    t0 = net.now
    sent_from_victim = 0
    for i in range(20):
        fake = Origin(1, f"fake{i % 4}", 1, 1, service_digest(()), 2)
        for data in (
            wire.encode(Alive(fake, "", 0, 2**40 + i), compact=True),
            wire.encode(Discovery(fake, "uuid:r1", 0, seq=i, multicast=False), compact=True),
            wire.encode(
                Discovery(fake, "uuid:r2", 0, want=wire.WANT_ALL, multicast=False), compact=True
            ),
        ):
            net.inject_all(data, VICTIM)
            sent_from_victim += len(data)
        net.run_for(BEACON / 2)
    net.run_for(4 * BEACON)
    for name in names:
        to_victim = sum(len(d) for t, d, dst in net.nodes[name].sent if dst == VICTIM and t >= t0)
        assert to_victim <= sent_from_victim, (name, to_victim, sent_from_victim)
        assert net.nodes[name].core.counters.rejects["amplification"] > 0
    assert net.all_see_all(names)


def test_plain_searches_one_answer_per_source_and_only_from_our_subnet() -> None:
    search = (
        b'M-SEARCH * HTTP/1.1\r\nHOST: 239.255.255.250:1900\r\nMAN: "ssdp:discover"\r\n'
        b"MX: 2\r\nST: ssdp:all\r\n\r\n"
    )
    net = SimNet(seed=311)
    fleet(net, 1, n_services=1)
    core = net.nodes["r1"].core
    core.set_subnet("10.1.0.0/24")
    near: Addr = ("10.1.0.200", 51234)
    far: Addr = ("192.0.2.9", 1900)
    for _ in range(50):
        net.inject("r1", search, near)
        net.inject("r1", search, far)
    to_near = [d for _, d, dst in net.nodes["r1"].sent if dst == near]
    assert len(to_near) == 1  # one answer, then at most one every 2 s
    assert not [d for _, d, dst in net.nodes["r1"].sent if dst == far]
    assert core.counters.rejects["off-subnet"] == 50


def test_multicast_searches_cost_one_whole_set_a_beacon_period() -> None:
    """At the product's 10 s beacon: two forged multicast searches a second from two
    addresses make each robot multicast its whole set at most once a beacon period."""
    net = SimNet(seed=312)
    names = ["r1", "r2", "r3"]
    for name in names:
        net.add(name, services=services(name, 40), beacon_interval=10.0, ping_interval=10.0)
    net.wait_until(lambda: net.all_see_all(names), timeout=20.0)
    net.run_for(20.0)
    t0 = net.now
    for _ in range(60):  # two searches a second for 30 s, from two forged robots
        for j in (0, 1):
            fake = Origin(1, f"searcher{j}", 1, 0, service_digest(()))
            search = wire.encode(Discovery(fake, wire.fleet_target(1), 1, want=wire.WANT_ALL))
            net.inject_all(search, (f"10.1.0.{90 + j}", 1900))
        net.run_for(0.5)
    elapsed = net.now - t0
    for name in names:
        firsts = [
            m
            for t, d, dst in net.nodes[name].sent
            if dst is None and t >= t0 and kind_of(d) == "update"
            if isinstance(m := wire.decode(d), Update) and m.part == 0
        ]
        assert len(firsts) <= elapsed / 10.0 + 1, (name, len(firsts), elapsed)


def test_unbelieved_parts_that_inflate_hold_a_bounded_amount() -> None:
    """Compact parts whose deflated JSON inflates a hundredfold, from fakes that never
    answer: what the core holds for them stays within UNPROVEN_BYTES."""
    net = SimNet(seed=313)
    fleet(net, 1, n_services=1)
    core: Core = net.nodes["r1"].core
    # 100 services of 2 KB of JSON each: deflated, half of them fit one datagram.
    svcs = [
        Service(f"s{i}", "big", "t", attributes={f"a{j}": "x" * 250 for j in range(8)})
        for i in range(100)
    ]
    for i in range(1024):
        origin = Origin(1, f"fake{i}", 1, 1, service_digest(svcs), 2)
        data = wire.encode_update_parts(origin, "http://x/", 0, svcs, compact=True)[0]
        if i == 0:
            part = wire.decode(data)
            assert isinstance(part, Update)
            assert sum(map(wire.service_json_size, part.services)) > 100 * len(data)
        net.inject("r1", data, (f"10.1.{1 + i // 200}.{i % 200 + 1}", 1900))
    held = sum(
        wire.service_json_size(s)
        for p in core.peers.values()
        if p.fetch is not None
        for part in p.fetch.got.values()
        for s in part
    )
    assert held <= UNPROVEN_BYTES
    assert core.counters.rejects["unproven-parts"] > 0


def test_a_sealed_datagram_names_its_recipient_and_sender() -> None:
    net = SimNet(seed=314)
    names = fleet(net, 2, n_services=2, keyring=keyed())
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    for data in unicasts(net, "r1", "r2")[-5:]:
        sealed = auth.seal_of(data)
        assert sealed is not None and not sealed.fleet
    for data in multicasts(net, "r1")[-3:]:
        sealed = auth.seal_of(data)
        assert sealed is not None and sealed.fleet


def _first_meeting(keyring: Keyring, a: str, b: str, seed: int) -> float:
    """Robots `a` and `b` (each already meeting a third, so their beacons ping) come into
    range of each other: how long after the first datagram one heard from the other both
    list each other."""
    net = SimNet(seed=seed)
    cfg = {"beacon_interval": BEACON, "keyring": keyring}
    net.blocked.add(frozenset((a, b)))
    for name in (a, b, "hub"):
        net.add(name, services=services(name, 3), **cfg)  # type: ignore[arg-type]
    net.wait_until(lambda: listed(net, a, "hub") and listed(net, b, "hub"), 4 * BEACON)
    net.run_for(5.37 * BEACON)  # (past the searches of a start, not in step with beacons)
    heard: list[float] = []

    def first(node: object, data: bytes, src: Addr) -> None:
        pair = {net.nodes[a].addr, net.nodes[b].addr}
        if not heard and node in (net.nodes[a], net.nodes[b]) and src in pair:
            heard.append(net.now)

    net.on_receive = first  # type: ignore[assignment]
    net.blocked.clear()
    net.wait_until(lambda: listed(net, a, b) and listed(net, b, a), 4 * BEACON, step=0.001)
    assert heard
    return net.now - heard[0]


def test_robots_that_meet_list_each_other_within_a_round_trip_of_the_first_beacon() -> None:
    # A first beacon does not pay for a padded challenge (no amplification), so the robot
    # that heard it invites one (`challenges.invite`): both list each other a few network delays
    # (1-4 ms here) later, not a beacon period later.  Ids of different lengths: the
    # invitation pays for the longer one's challenge.
    for keyring in (Keyring(), keyed()):
        for seed, (a, b) in enumerate([("r1", "r2"), ("r1", "robot-with-a-much-longer-id-7")]):
            took = _first_meeting(keyring, a, b, seed=310 + seed)
            assert took < 0.05 * BEACON, (keyring.signs, a, b, took)
