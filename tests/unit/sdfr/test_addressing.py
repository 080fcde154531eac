"""Address self-configuration in virtual time: robots on an ARP broadcast domain."""

from __future__ import annotations

import heapq
import itertools
import random
from collections.abc import Callable
from ipaddress import IPv4Address

import pytest

from sdfr.protocol.addressing import (
    ZERO,
    AddrConfig,
    Addressing,
    Arp,
    Assign,
    Release,
    State,
    candidates,
)


class Host:
    """A robot: the addressing machine plus what its kernel does with ARP."""

    def __init__(self, net: ArpNet, name: str, mac: str, group: int) -> None:
        self.net = net
        self.name = name
        self.mac = mac
        self.group = group
        self.machine = Addressing(AddrConfig(fleet=7, mac=mac), random.Random(hash(name) & 0xFFFF))
        self.assigned: set[IPv4Address] = set()
        self.armed: float | None = None

    def pump(self) -> None:
        for action in self.machine.actions():
            if isinstance(action, Assign):
                self.assigned.add(action.ip)
            elif isinstance(action, Release):
                self.assigned.discard(action.ip)
        for send in self.machine.arp_to_send():
            sender = ZERO if send.kind == "probe" else send.ip
            self.net.broadcast(self, Arp(1, self.mac, sender, send.ip))
        deadline = self.machine.next_deadline()
        if deadline is not None and deadline != self.armed:
            self.armed = deadline

            def fire(when: float = deadline) -> None:
                if self.armed == when:
                    self.armed = None
                    self.machine.handle_timer(self.net.now)
                    self.pump()

            self.net.at(deadline, fire)

    def hear(self, pkt: Arp) -> None:
        self.machine.handle_arp(pkt, self.net.now)
        self.pump()
        # The kernel answers requests for an address it holds (a probe finds the holder).
        if pkt.op == 1 and pkt.target_ip in self.assigned and pkt.sender_mac != self.mac:
            self.net.broadcast(self, Arp(2, self.mac, pkt.target_ip, pkt.sender_ip))


class ArpNet:
    def __init__(self, loss: float = 0.0, seed: int = 1) -> None:
        self.now = 0.0
        self.hosts: list[Host] = []
        self.loss = loss
        self.rng = random.Random(seed)
        self.sent: list[tuple[float, str, Arp]] = []
        self.split = False
        self._q: list[tuple[float, int, Callable[[], None]]] = []
        self._seq = itertools.count()

    def add(self, name: str, mac: str, group: int = 0, current: IPv4Address | None = None) -> Host:
        host = Host(self, name, mac, group)
        self.hosts.append(host)
        if current is not None:
            host.assigned.add(current)
        host.machine.start(self.now, current)
        host.pump()
        return host

    def at(self, t: float, fn: Callable[[], None]) -> None:
        heapq.heappush(self._q, (t, next(self._seq), fn))

    def broadcast(self, src: Host, pkt: Arp) -> None:
        self.sent.append((self.now, src.name, pkt))
        for h in self.hosts:
            if h is src or (self.split and h.group != src.group):
                continue
            if self.rng.random() < self.loss:
                continue
            self.at(self.now + 0.001, lambda h=h: h.hear(pkt))

    def run(self, until: float) -> None:
        while self._q and self._q[0][0] <= until:
            t, _, fn = heapq.heappop(self._q)
            self.now = max(self.now, t)
            fn()
        self.now = until


def test_candidates_are_documented_and_stable() -> None:
    seq = candidates(3, "02:00:00:00:12:34")
    first = next(seq)
    assert first == IPv4Address("10.3.19.53")  # 1 + 0x12 % 254, 1 + 0x34 % 254
    rest = [next(seq) for _ in range(500)]
    assert len(set(rest)) == 500 and first not in rest
    for ip in [first, *rest]:
        x, y = ip.packed[2], ip.packed[3]
        assert 1 <= x <= 254 and 1 <= y <= 254
    assert list(itertools.islice(candidates(3, "02:00:00:00:12:34"), 5)) == [first, *rest[:4]]
    # 0 and 255 octets map inside 1..254.
    assert next(candidates(1, "02:00:00:00:00:ff")) == IPv4Address("10.1.1.2")
    with pytest.raises(ValueError):
        next(candidates(1, "nonsense"))


def test_lone_robot_probes_then_announces_then_holds() -> None:
    net = ArpNet()
    h = net.add("a", "02:00:00:00:12:34")
    net.run(5.0)
    assert h.machine.state is State.BOUND and h.assigned == {IPv4Address("10.7.19.53")}
    kinds = [("probe" if p.sender_ip == ZERO else "announce") for _, _, p in net.sent]
    assert kinds == ["probe"] * 3 + ["announce"] * 2
    probe_times = [t for t, _, p in net.sent]
    assert probe_times[-1] < 1.5  # our timers are faster than RFC 5227's ~7 s


def test_six_robots_all_bound_to_distinct_derived_addresses() -> None:
    net = ArpNet(seed=2)
    hosts = [net.add(f"r{i}", f"02:00:00:00:{i:02x}:{i * 7:02x}") for i in range(1, 7)]
    net.run(3.0)
    ips = [h.machine.bound for h in hosts]
    assert all(ip is not None for ip in ips) and len(set(ips)) == 6
    assert all(h.machine.bound == next(candidates(7, h.mac)) for h in hosts)


def test_a_robot_started_onto_a_used_address_never_takes_it() -> None:
    net = ArpNet()
    holder = net.add("holder", "02:10:00:00:12:34")
    net.run(2.0)
    # Lower MAC, same derived address: the probe must still find the holder and move on.
    late = net.add("late", "02:00:00:00:12:34")
    net.run(6.0)
    assert holder.machine.bound == IPv4Address("10.7.19.53")
    assert late.machine.bound not in (None, holder.machine.bound)
    assert IPv4Address("10.7.19.53") not in late.assigned  # never assigned, not even briefly
    assert [c.phase for c in late.machine.conflicts] == ["probe"]


def test_merge_conflict_lower_mac_keeps_exactly_one_moves_bounded_packets() -> None:
    net = ArpNet()
    net.split = True
    low = net.add("low", "02:00:00:00:12:34", group=0)
    high = net.add("high", "02:aa:00:00:12:34", group=1)
    net.run(3.0)
    shared = IPv4Address("10.7.19.53")
    assert low.machine.bound == high.machine.bound == shared
    net.split = False
    merged = net.now
    # The discovery layer hears a datagram from its own address and raises suspicion.
    low.machine.suspect(net.now)
    low.pump()
    high.machine.suspect(net.now)
    high.pump()
    net.run(merged + 3.0)
    assert low.machine.bound == shared and shared in low.assigned
    assert high.machine.bound not in (None, shared) and shared not in high.assigned
    after = [p for t, _, p in net.sent if t >= merged]
    assert len(after) <= 8  # 2 announcements, then 3 probes + 2 announcements of the mover
    net.run(merged + 60.0)
    assert low.machine.bound == shared and high.machine.bound != shared  # no ping-pong


def test_simultaneous_probes_lower_mac_goes_on() -> None:
    net = ArpNet()
    a = net.add("a", "02:00:00:00:12:34")
    b = net.add("b", "02:01:00:00:12:34")
    net.run(5.0)
    assert a.machine.bound == IPv4Address("10.7.19.53")
    assert b.machine.bound is not None and b.machine.bound != a.machine.bound


def test_restart_keeps_its_current_address_by_announcing() -> None:
    net = ArpNet()
    mine = next(candidates(7, "02:00:00:00:12:34"))
    h = net.add("a", "02:00:00:00:12:34", current=mine)
    net.run(2.0)
    assert h.machine.bound == mine
    assert all(p.sender_ip == mine for _, _, p in net.sent)  # no probes, announcements only


def test_too_many_conflicts_rate_limit() -> None:
    cfg = AddrConfig(fleet=7, mac="02:00:00:00:00:01", max_conflicts=2, rate_limit_interval=30.0)
    m = Addressing(cfg, random.Random(1))
    m.start(0.0)
    for _ in range(2):
        assert m.state is State.PROBING and m.ip is not None
        m.handle_arp(Arp(2, "02:99:00:00:00:01", m.ip, m.ip), 0.1)
    assert m.state is State.WAITING
    assert m.next_deadline() == pytest.approx(0.1 + 30.0)
    m.handle_timer(30.1)
    assert m.state is State.PROBING


def test_arp_loss_still_converges() -> None:
    net = ArpNet(loss=0.3, seed=5)
    hosts = [net.add(f"r{i}", f"02:00:00:00:{i:02x}:{i:02x}") for i in range(1, 7)]
    net.run(5.0)
    assert len({h.machine.bound for h in hosts}) == 6


def test_refresh_announces_once_per_interval_only_when_bound() -> None:
    m = Addressing(
        AddrConfig(fleet=7, mac="02:00:00:00:00:01", refresh_interval=1.0), random.Random(1)
    )
    m.refresh(0.0)
    assert m.arp_to_send() == []  # not bound yet: nothing to announce
    m.start(0.0, current=next(candidates(7, "02:00:00:00:00:01")))
    for t in (0.0, 0.1, 0.2):
        m.handle_timer(t)
    assert m.state is State.BOUND
    m.arp_to_send()
    m.refresh(1.0)
    m.refresh(1.5)
    m.refresh(2.1)
    sent = m.arp_to_send()
    assert [s.kind for s in sent] == ["announce", "announce"]
