"""The protocol core driven in virtual time: fleets of cores on an in-memory medium."""

from __future__ import annotations

import pytest

from sdfr import wire
from sdfr.protocol import Core, CoreConfig, beacons, updates
from sdfr.protocol.config import MAX_PINGS
from sdfr.protocol.core import BYEBYE_COPIES
from sdfr.protocol.peers import _Ping
from sdfr.records.model import PeerRecord, Service
from sdfr.testing.simnet import BEACON, SimNet, fleet, kind_of, sent, services
from tests.support.wire_data import noisy_services


def updates_sent(net: SimNet, since: float) -> int:
    return sum(
        1
        for node in net.nodes.values()
        for t, data, _ in node.sent
        if t >= since and kind_of(data) in ("update", "delta")
    )


def test_startup_six_robots_converge_within_2s_with_100_services_each() -> None:
    net = SimNet(seed=3)
    names = fleet(net, 6)
    took = net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    assert took < 2.0
    # A set of 100 services does not fit one datagram: it went out in parts.
    parts = updates.update_parts(net.nodes["r1"].core)
    assert len(parts) > 1 and all(len(p) <= wire.MAX_DATAGRAM for p in parts)


def test_every_datagram_fits_the_radio_budget() -> None:
    net = SimNet(seed=4)
    fleet(net, 4)
    net.run_for(10 * BEACON)
    sizes = [len(d) for n in net.nodes.values() for _, d, _ in n.sent]
    assert sizes and max(sizes) <= wire.MAX_DATAGRAM


def test_join_is_listed_by_all_within_1s_and_lists_all() -> None:
    net = SimNet(seed=5)
    names = fleet(net, 5)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(3.3 * BEACON)
    net.add("r6", services=services("r6"), beacon_interval=BEACON, ping_interval=BEACON / 2)
    took = net.wait_until(lambda: net.all_see_all([*names, "r6"]), timeout=1.0)
    assert took <= 1.0


def test_byebye_removes_at_once_and_keeps_history() -> None:
    net = SimNet(seed=6)
    names = fleet(net, 3)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.stop("r3")
    took = net.wait_until(lambda: not net.sees("r1", "r3") and not net.sees("r2", "r3"), 0.2)
    assert took < 0.05
    peer = net.nodes["r1"].core.peers["r3"]
    assert not peer.reachable and len(peer.services) == 100  # still in history


def test_late_datagram_after_byebye_does_not_resurrect() -> None:
    net = SimNet(seed=7)
    names = fleet(net, 2)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    alive = wire.encode(
        wire.Alive(net.nodes["r2"].core._origin(), net.nodes["r2"].core.location, 3)
    )
    net.stop("r2")
    net.run_for(0.05)
    net.inject("r1", alive, net.nodes["r2"].addr)
    assert not net.sees("r1", "r2")


def test_silent_death_unreachable_within_3_beacons_indicator_falls() -> None:
    net = SimNet(seed=8)
    names = fleet(net, 3)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(6 * BEACON)
    before = net.nodes["r1"].core.peers["r3"].indicator
    assert before == 1.0
    net.kill("r3")
    took = net.wait_until(lambda: not net.sees("r1", "r3") and not net.sees("r2", "r3"), 3 * BEACON)
    assert took <= 3 * BEACON
    net.run_for(2 * BEACON)  # outstanding pings settle as lost
    peer = net.nodes["r1"].core.peers["r3"]
    assert peer.indicator is not None and peer.indicator < before
    assert len(peer.services) == 100


@pytest.mark.parametrize(
    "ping_interval", [BEACON / 2, BEACON], ids=["unicast-pings", "beacon-pings"]
)
def test_a_busy_robot_that_answers_late_stays_listed_and_its_indicator_says_so(
    ping_interval: float,
) -> None:
    """r2 answers r1 a second and a half late (a busy CPU: past the ping timeout, within the
    proof window): r1 keeps it listed throughout, its indicator counts the late answers as
    lost, and once r2 dies r1 still drops it within the miss limit."""
    net = SimNet(seed=21)
    names = fleet(net, 3, n_services=2, ping_interval=ping_interval)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    core = net.nodes["r1"].core
    assert core.config.ping_timeout < 1.5 < core.config.proof_window()
    net.pair_delay[("r2", "r1")] = 1.5
    t0 = net.now
    flaps = []
    while net.now < t0 + 20 * BEACON:
        net.run_for(0.05)
        if not net.sees("r1", "r2"):
            flaps.append(round(net.now - t0, 2))
    assert flaps == []
    peer = core.peers["r2"]
    assert peer.indicator == 0.0  # every answer came after the ping timeout
    assert net.sees("r1", "r3") and core.peers["r3"].indicator == 1.0
    killed = net.now
    net.kill("r2")
    # Its last answer (to a ping sent before it died) keeps it at most a proof window.
    took = net.wait_until(lambda: not net.sees("r1", "r2"), 3 * BEACON + 0.05)
    assert net.now - killed <= core.config.proof_window() + 0.05, took


def test_pings_kept_for_a_late_answer_are_bounded_and_the_oldest_go_first() -> None:
    table: dict[int, _Ping] = {}
    for seq in range(MAX_PINGS + 10):
        beacons.keep_late(table, seq, _Ping("r2", float(seq), ("10.1.0.2", 1900)))
    assert len(table) == MAX_PINGS and min(table) == 10


def test_indicator_keeps_the_pings_lost_in_an_outage_and_recovers() -> None:
    net = SimNet(seed=18)
    # A window the pings before and during the outage do not fill: the new ones then add to it.
    names = fleet(net, 2, n_services=2, ping_window=40)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(6 * BEACON)
    assert net.nodes["r1"].core.peers["r2"].indicator == 1.0
    net.partition(["r1"], ["r2"])
    net.wait_until(lambda: not net.sees("r1", "r2"), 3 * BEACON + 0.5)
    net.run_for(BEACON)
    fallen = net.nodes["r1"].core.peers["r2"].indicator
    assert fallen is not None and fallen < 1.0
    net.merge()
    net.wait_until(lambda: net.sees("r1", "r2"), 2 * BEACON)
    # Back in range, the window still holds the pings lost while apart: the indicator starts
    # from there (plus the answered ping that listed it again) and climbs as new pings
    # succeed, rather than jumping back to 1.0.
    peer = net.nodes["r1"].core.peers["r2"]
    assert peer.indicator is not None
    assert fallen <= peer.indicator <= fallen + 1 / len(peer.pings) < 1.0
    net.run_for(3 * BEACON)
    assert peer.indicator is not None and fallen < peer.indicator < 1.0


def test_a_ping_rides_on_the_reply_to_the_peers_ping() -> None:
    net = SimNet(seed=19)
    names = fleet(net, 2, n_services=2, ping_window=1000)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(4 * BEACON)
    interval = BEACON / 2
    settled = {n: len(net.nodes[n].core.peers[o].pings) for n, o in (("r1", "r2"), ("r2", "r1"))}
    t0 = net.now
    rounds = 60
    net.run_for(rounds * interval)
    out = [d for n in names for t, d, _ in net.nodes[n].sent if t >= t0]
    pings = sum(kind_of(d) == "ping" for d in out)
    replies = [d for d in out if kind_of(d) == "reply"]
    riding = sum(b"X-SDFR-PING" in d for d in replies)
    replies = len(replies)
    # Each robot still gets about one round trip per ping interval...
    for (a, b), before in zip((("r1", "r2"), ("r2", "r1")), settled.values(), strict=True):
        peer = net.nodes[a].core.peers[b]
        got = len(peer.pings) - before
        assert rounds * 0.9 <= got <= rounds * 1.15, (a, got)
        assert peer.indicator == 1.0
    # ... from three datagrams a round (a ping, a reply carrying the other's ping, its reply)
    # rather than four.
    assert riding >= rounds * 0.8
    assert pings + replies <= 3.3 * rounds * 1.1, (pings, replies)


def test_a_round_trip_is_proven_while_pings_come_back() -> None:
    net = SimNet(seed=20)
    names = fleet(net, 2, n_services=2)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(2 * BEACON)
    core, r2 = net.nodes["r1"].core, net.nodes["r2"].addr
    assert core.round_trip_proven(r2, net.now)
    assert not core.round_trip_proven(("10.9.9.9", 1900), net.now)
    net.partition(["r1"], ["r2"])
    net.run_for(2.5 * BEACON)  # 5 ping intervals without an answer
    assert not core.round_trip_proven(r2, net.now)


def test_partition_and_merge_no_refetch_no_ghosts() -> None:
    net = SimNet(seed=9)
    names = fleet(net, 6)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    a, b = names[:3], names[3:]
    net.partition(a, b)
    net.wait_until(
        lambda: all(
            net.sees(x, y) == ((x in a) == (y in a)) for x in names for y in names if x != y
        ),
        timeout=3 * BEACON,
    )
    net.run_for(5 * BEACON)
    merged_at = net.now
    net.merge()
    took = net.wait_until(lambda: net.all_see_all(names), timeout=BEACON + 1.0)
    assert took <= BEACON + 1.0
    assert updates_sent(net, merged_at) == 0  # unchanged sets are not fetched again
    for x in names:
        assert sorted(net.nodes[x].core.peers) == sorted(n for n in names if n != x)


def test_merge_with_changed_services_fetches_by_unicast() -> None:
    net = SimNet(seed=10)
    names = fleet(net, 4, n_services=10)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(3 * BEACON)
    net.partition(["r1", "r2"], ["r3", "r4"])
    net.run_for(0.5)
    new = tuple(services("r4", 12, tag="b"))
    net.set_services("r4", 2, new)
    net.wait_until(lambda: net.nodes["r3"].core.peers["r4"].services == new, timeout=0.5)
    assert net.nodes["r1"].core.peers["r4"].services == tuple(services("r4", 10))
    merged_at = net.now
    net.merge()
    net.wait_until(lambda: net.all_see_all(names), timeout=BEACON + 1.0)
    fetches = [
        dst
        for t, data, dst in net.nodes["r1"].sent
        if t >= merged_at and data.startswith(b"M-SEARCH") and b"X-SDFR-WANT" in data
    ]
    assert fetches and all(dst == net.nodes["r4"].addr for dst in fetches)


def test_service_churn_seen_within_500ms() -> None:
    net = SimNet(seed=11)
    names = fleet(net, 4, n_services=20)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    for version in range(2, 12):
        new = services("r2", 20 + version)
        net.set_services("r2", version, new)
        took = net.wait_until(
            lambda new=new: all(
                net.nodes[x].core.peers["r2"].services == tuple(new) for x in names if x != "r2"
            ),
            timeout=0.5,
        )
        assert took <= 0.5
        net.run_for(0.3)


def test_burst_of_changes_is_coalesced() -> None:
    net = SimNet(seed=12)
    names = fleet(net, 2, n_services=5)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    t0 = net.now
    for version in range(2, 22):
        net.set_services("r1", version, services("r1", 5 + version))
    net.wait_until(lambda: net.all_see_all(names), timeout=0.5)
    versions = {
        msg.origin.version
        for t, data, _ in net.nodes["r1"].sent
        if t >= t0 and isinstance(msg := wire.decode(data), wire.Update)
    }
    assert versions == {21}  # one announcement for the whole burst


def test_reboot_replaces_the_service_set_never_merges() -> None:
    net = SimNet(seed=13)
    names = fleet(net, 3, n_services=10)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    fresh = services("r3", 4, tag="new")
    net.restart("r3", boot_id=2, graceful=False, services=fresh, version=1)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    for x in ("r1", "r2"):
        peer = net.nodes[x].core.peers["r3"]
        assert peer.services == tuple(fresh) and peer.boot_id == 2


def test_lost_parts_are_re_requested() -> None:
    net = SimNet(seed=14)
    dropped: list[bytes] = []

    def drop_second_part_once(src: str, dst: str, data: bytes) -> bool:
        msg = wire.decode(data)
        second = isinstance(msg, wire.Update) and msg.base is None and msg.part == 1
        if src == "r2" and second and not dropped:
            dropped.append(data)
            return False
        return True

    net.filter = drop_second_part_once
    names = ["r1", "r2"]
    for name in names:  # sets that barely deflate: several parts, compact or not
        net.add(name, services=noisy_services(40, seed=len(net.nodes)), beacon_interval=BEACON,
                ping_interval=BEACON / 2)  # fmt: skip
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    assert dropped
    asked = [wire.decode(d) for _, d, dst in sent(net, "r1", "fetch")]
    assert any(isinstance(a, wire.Discovery) and a.want == (1,) for a in asked), (
        "the missing part was not asked for by number"
    )


def test_unknown_version_is_asked_by_unicast() -> None:
    net = SimNet(seed=15)
    names = fleet(net, 3, n_services=5)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    # r1 hears nothing of r3 while r3 announces its new set: it learns of version 2 later
    # (from a beacon or a ping) and must ask r3 for it.
    net.filter = lambda src, dst, data: not (dst == "r1" and src == "r3")
    net.set_services("r3", 2, services("r3", 6))
    net.run_for(0.4)  # (past the change's multicast delta and its repeat, `update_gap` on)
    net.filter = None
    assert net.nodes["r1"].core.peers["r3"].version == 1
    peer = net.nodes["r1"].core.peers["r3"]
    net.wait_until(lambda: peer.version == 2 and peer.current, timeout=2 * BEACON)
    asks = [
        (d, dst)
        for _, d, dst in net.nodes["r1"].sent
        if d.startswith(b"M-SEARCH") and b"X-SDFR-WANT" in d and dst is not None
    ]
    assert asks and all(dst == net.nodes["r3"].addr for _, dst in asks)
    # Nobody else had to re-announce by multicast.
    assert net.nodes["r2"].core.peers["r3"].current


@pytest.mark.parametrize("seed", [21, 22, 23])
def test_thirty_percent_loss_converges_without_flapping(seed: int) -> None:
    net = SimNet(seed=seed, loss=0.3)
    # 200 pings a window: the sampling noise (3.5 points) stays well inside the bound.
    names = fleet(net, 6, n_services=30, ping_window=200)
    # No deadline for converging under loss (the `lossy` scenario allows 20 beacons, so that
    # only a failure to converge fails it): 1.5-13 s in 80 seeded runs.
    net.wait_until(lambda: net.all_see_all(names), timeout=20 * BEACON)
    flaps = {(x, y): 0 for x in names for y in names if x != y}
    state = {k: True for k in flaps}
    duration = 110.0 * BEACON
    end = net.now + duration
    while net.now < end:
        net.run_for(0.05)
        for x, y in flaps:
            s = net.sees(x, y)
            if state[(x, y)] and not s:
                flaps[(x, y)] += 1
            state[(x, y)] = s
    # "no reachable robot flaps out more than once a minute": a minute is 60 beacons here,
    # ten times stricter than the product's default 10 s beacon would be.
    assert max(flaps.values()) <= 1, flaps
    for x in names:
        for y in names:
            if x != y:
                ind = net.nodes[x].core.peers[y].indicator
                # A ping and its reply both cross the lossy medium: 0.7 * 0.7 get through.
                assert ind is not None and abs(ind - 0.49) <= 0.15, (x, y, ind)


def test_duplicates_and_reordering_converge_to_the_right_sets() -> None:
    net = SimNet(seed=31, duplicate=0.3, delay=(0.001, 0.3))
    names = fleet(net, 4, n_services=40)
    net.wait_until(lambda: net.all_see_all(names), timeout=3.0)
    for v in range(2, 6):
        net.set_services("r1", v, services("r1", 40 + v))
        net.run_for(0.05)
    net.wait_until(lambda: net.all_see_all(names), timeout=3.0)
    net.run_for(5 * BEACON)
    assert net.all_see_all(names)


def test_malformed_and_foreign_datagrams_are_counted_not_raised() -> None:
    net = SimNet(seed=41)
    names = fleet(net, 2, n_services=3)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    core = net.nodes["r1"].core
    junk = [
        b"",
        b"\x00\xff" * 50,
        b"GET / HTTP/1.1\r\n\r\n",
        b"NOTIFY * HTTP/1.1\r\nHOST: 239.255.255.250:1900\r\nNT: upnp:rootdevice\r\n"
        b"NTS: ssdp:alive\r\nUSN: uuid:router::upnp:rootdevice\r\nLOCATION: http://x/\r\n\r\n",
        b"x" * 5000,
    ]
    other_fleet = wire.encode(
        wire.Alive(wire.Origin(9, "stranger", 1, 1, "0" * 16), "http://10.9.0.1/", 30)
    )
    for data in [*junk, other_fleet]:
        net.inject("r1", data, ("10.1.0.77", 1900))
    assert sum(core.counters.rejects.values()) >= len(junk)
    assert core.counters.rejects["other-fleet"] == 1
    assert "stranger" not in core.peers
    net.run_for(3 * BEACON)
    assert net.all_see_all(names)


def test_plain_ssdp_client_gets_a_unicast_200_ok() -> None:
    net = SimNet(seed=42)
    fleet(net, 2, n_services=3)
    search = (
        b'M-SEARCH * HTTP/1.1\r\nHOST: 239.255.255.250:1900\r\nMAN: "ssdp:discover"\r\n'
        b"MX: 2\r\nST: ssdp:all\r\n\r\n"
    )
    client = ("10.1.0.200", 51234)
    net.inject("r1", search, client)
    replies = [d for _, d, dst in net.nodes["r1"].sent if dst == client]
    assert len(replies) == 1 and replies[0].startswith(b"HTTP/1.1 200 OK")
    msg = wire.decode(replies[0])
    assert isinstance(msg, wire.Response)
    assert msg.location.startswith("http://10.1.0.1:")
    # A search for something we are not is not answered.
    net.inject("r1", search.replace(b"ssdp:all", b"urn:schemas-upnp-org:device:Printer:1"), client)
    assert len([d for _, d, dst in net.nodes["r1"].sent if dst == client]) == 1


def test_restored_history_revalidates_without_refetch() -> None:
    net = SimNet(seed=51)
    names = fleet(net, 3, n_services=20)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    r1 = net.nodes["r1"].core
    saved: list[PeerRecord] = [r1.view(p) for p in r1.peers.values()]
    # r1 restarts (new boot) with its history restored from disk.
    node = net.restart("r1", boot_id=2, graceful=False)
    node.core.restore(saved)
    assert not node.core.peers["r2"].reachable and len(node.core.peers["r2"].services) == 20
    t0 = net.now
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    fetch_asks = [d for t, d, dst in node.sent if t >= t0 and b"X-SDFR-WANT" in d and dst]
    assert fetch_asks == []  # r2 and r3 were re-validated, not re-fetched


def test_core_next_deadline_and_idle_core() -> None:
    cfg = CoreConfig(fleet=1, robot_id="solo", beacon_interval=10.0)
    import random

    core = Core(cfg, boot_id=1, rng=random.Random(1), location="http://10.1.0.1:8701/")
    assert core.next_deadline() is None
    core.start(0.0)
    out = core.datagrams_to_send()
    kinds = sorted(wire.decode(d).__class__.__name__ for d, _ in out)
    assert kinds == ["Discovery", "Update"]
    deadline = core.next_deadline()
    assert deadline is not None and 0 < deadline <= 10.0
    core.stop(1.0)
    bye = ["Byebye"] * BYEBYE_COPIES  # (back to back: nothing repairs a lost one)
    assert BYEBYE_COPIES >= 2
    assert [wire.decode(d).__class__.__name__ for d, _ in core.datagrams_to_send()] == bye
    assert core.next_deadline() is None


def test_a_single_change_goes_out_as_one_small_delta() -> None:
    net = SimNet(seed=61)
    names = fleet(net, 3)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(2 * BEACON)
    t0 = net.now
    bigger = [*services("r1"), Service("extra", "extra", "sensor.extra")]
    net.set_services("r1", 2, bigger)
    net.wait_until(lambda: net.all_see_all(names), timeout=0.5)
    deltas = [d for _, d, _ in sent(net, "r1", "delta", since=t0)]
    assert len(deltas) == 1 and sent(net, "r1", "update", since=t0) == []
    packed = wire.decode(deltas[0])
    assert isinstance(packed, wire.Update)
    msg = wire.unpack_delta(packed, services("r1"))  # deflated against the set it changes
    assert isinstance(msg, wire.Update) and msg.base == 1 and msg.services == (bigger[-1],)
    assert len(deltas[0]) < 150  # the compact form: one header line and the service
    net.set_services("r1", 3, bigger[1:])  # an unpublish is a delta too
    net.wait_until(lambda: net.all_see_all(names), timeout=0.5)
    deltas = [d for _, d, _ in sent(net, "r1", "delta", since=t0)]
    packed = wire.decode(deltas[-1])
    assert len(deltas) == 2 and isinstance(packed, wire.Update)
    msg = wire.unpack_delta(packed, bigger)
    assert isinstance(msg, wire.Update) and msg.removed == ("r1-s0",)


def test_a_delta_without_its_base_is_caught_up_by_unicast() -> None:
    net = SimNet(seed=62)
    names = fleet(net, 3, n_services=30)
    net.wait_until(lambda: net.all_see_all(names), timeout=2.0)
    net.run_for(2 * BEACON)
    net.filter = lambda src, dst, data: not (dst == "r2" and src == "r1")
    net.set_services("r1", 2, services("r1", 31))
    net.run_for(0.1)
    net.filter = None
    assert net.nodes["r2"].core.peers["r1"].version == 1  # r2 knows nothing of version 2
    t0 = net.now
    net.set_services("r1", 3, services("r1", 32))
    net.wait_until(lambda: net.all_see_all(names), timeout=1.0)
    asks = [wire.decode(d) for _, d, _ in sent(net, "r2", "fetch", since=t0)]
    # r2 missed base 2: it asked r1 for version 3 saying it holds version 1 ...
    assert asks and all(isinstance(a, wire.Discovery) and a.have == 1 for a in asks)
    # ... and got what changed since, in one datagram, not the set's 3 parts.
    r2 = net.nodes["r2"].addr
    to_r2 = [d for t, d, dst in net.nodes["r1"].sent if t >= t0 and dst == r2]
    # (r1's answers to r2's pings may tell it of version 2 first: then one catch-up to 2, and
    # the multicast delta 2 -> 3 does the rest.)
    caught = [d for d in to_r2 if kind_of(d) == "delta"]
    assert len(caught) == 1 and not [d for d in to_r2 if kind_of(d) == "update"]
    msg = wire.decode(caught[0])
    assert isinstance(msg, wire.Update) and msg.base == 1 and msg.origin.version in (2, 3)
    assert len(caught[0]) < sum(map(len, updates.update_parts(net.nodes["r1"].core, True))) / 2
