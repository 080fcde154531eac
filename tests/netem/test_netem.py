"""The netem tier: netlab's link shaping through the kernel's sch_netem, measured for real.

This machine's kernel has no sch_netem, so here these tests skip (saying why);
`make test-netem` (scripts/vm.sh netem) boots a Debian kernel under virtme-ng
and runs them inside it. On a kernel that has netem they run directly, as root.

What to expect follows from how `Lab.shape` realises a shape (netlab/shaping.py):
the robot's link is shaped in both directions, by one netem qdisc on its eth0
(what it sends) and one on its port in the air namespace (what it receives).
So, with r1 shaped and r2 clean:

* delay 50 ms: a ping r1->r2 crosses r1's link twice (request out, reply in),
  so its round trip is the baseline + 100 ms; a ping r2->r1 too.
* loss 30 %: a one-way datagram r1->r2 crosses r1's link once (eth0), and one
  r2->r1 crosses it once (the air port): 30 % each way. (A round trip would
  lose 1 - 0.7² = 51 %.)
* no parameters: both qdiscs go, and the link is as clean as before.

The datagrams are sent and counted from this process through sockets made
inside the robots' namespaces: Python starts slowly in the emulated VM, and
kernel receive timestamps make the rate measurement independent of it.
"""

from __future__ import annotations

import functools
import itertools
import re
import socket
import statistics
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from netlab import Lab, kernel, naming
from netlab.doctor import capabilities

pytestmark = [pytest.mark.root, pytest.mark.netem]

GROUP, PORT = "239.255.255.250", 1902  # not sdfrd's port: no daemon runs here anyway
HEADER = struct.Struct("!5sII")  # magic, run, sequence number
MAGIC = b"NETEM"
FRAME_OVERHEAD = 14 + 20 + 8  # Ethernet, IPv4, UDP: what a qdisc counts besides the payload
# Linux socket options Python does not name (asm-generic values, as on x86-64).
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)
QUIET = 1.0  # a receiver is done when nothing more arrives for this long

_runs = itertools.count(1)
_TIME_RE = re.compile(r"time=([\d.]+) ms")


def lab_name() -> str:
    return naming.unique_lab_name("n")


@dataclass
class Received:
    """Datagrams of one run that reached the receiver, in arrival order."""

    seqs: list[int] = field(default_factory=list)
    stamps: list[float] = field(default_factory=list)  # kernel arrival times, seconds
    intact: bool = True  # every payload was exactly what was sent

    @property
    def count(self) -> int:
        return len(self.seqs)

    def mbit_per_s(self, size: int) -> float:
        """Rate of the arrivals, counting whole frames of `size`-byte payloads."""
        span = max(self.stamps) - min(self.stamps)
        assert span > 0, f"{self.count} datagrams arrived at once"
        return (self.count - 1) * (size + FRAME_OVERHEAD) * 8 / span / 1e6


class Endpoint:
    """A UDP socket made inside a robot's namespace, joined to GROUP on its eth0."""

    def __init__(self, lab: Lab, robot: str) -> None:
        self.robot = robot
        self.ip = lab.robot(robot).ip
        with kernel.inside(lab.robot(robot).ns):  # the socket stays in that namespace
            ifindex = socket.if_nametoindex(naming.ROBOT_IFACE)
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, 16 << 20)  # holds a whole run
        s.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        s.bind(("0.0.0.0", PORT))
        any_addr = socket.inet_aton("0.0.0.0")
        mreqn = struct.pack("4s4si", socket.inet_aton(GROUP), any_addr, ifindex)
        s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreqn)
        s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, mreqn)
        s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 0)
        s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
        self.sock = s

    def drain(self) -> None:
        self.sock.setblocking(False)
        try:
            while True:
                self.sock.recv(65535)
        except BlockingIOError:
            pass
        finally:
            self.sock.setblocking(True)

    def collect(self, run: int, src: str, size: int) -> Received:
        got = Received()
        self.sock.settimeout(QUIET)
        while True:
            try:
                data, anc, _flags, (host, _) = self.sock.recvmsg(65535, socket.CMSG_SPACE(16))
            except TimeoutError:
                return got
            if host != src or len(data) < HEADER.size:
                continue
            magic, got_run, seq = HEADER.unpack_from(data)
            if magic != MAGIC or got_run != run:
                continue  # a late datagram of an earlier run
            got.seqs.append(seq)
            got.intact &= data == payload(run, seq, size)
            stamps = [
                struct.unpack("qq", cdata[:16])
                for level, kind, cdata in anc
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS
            ]
            assert stamps, "no receive timestamp (SO_TIMESTAMPNS)"
            got.stamps.append(stamps[0][0] + stamps[0][1] / 1e9)

    def close(self) -> None:
        self.sock.close()


@functools.cache
def _filler(n: int) -> bytes:
    return bytes(i % 251 for i in range(n))


def payload(run: int, seq: int, size: int) -> bytes:
    """`size` bytes: the header, then a known pattern (emulated Python is slow: reuse it)."""
    return HEADER.pack(MAGIC, run, seq) + _filler(size - HEADER.size)


def send(
    src: Endpoint, dst: Endpoint, count: int, *, size: int = 64, gap: float = 0.0005
) -> Received:
    """Send `count` datagrams src -> dst (`gap` s apart, 0: back to back); what arrived."""
    dst.drain()
    run = next(_runs)
    for seq in range(count):
        src.sock.sendto(payload(run, seq, size), (GROUP, PORT))
        if gap:
            time.sleep(gap)
    return dst.collect(run, src.ip, size)


def rtts(lab: Lab, a: str, b: str, count: int = 10, interval: float = 0.1) -> list[float]:
    """Round-trip times in ms of `count` pings a -> b; every one must be answered."""
    argv = ["ping", "-n", "-c", str(count), "-i", str(interval), "-W", "2", lab.robot(b).ip]
    res = lab.exec(a, argv, timeout=count * interval + 30)
    times = [
        float(m.group(1))
        for line in res.stdout.splitlines()
        if "DUP!" not in line and (m := _TIME_RE.search(line))
    ]
    assert len(times) == count, f"{count} pings {a}->{b}, {len(times)} answered:\n{res.stdout}"
    return times


def qdisc(lab: Lab, robot: str, side: str) -> str:
    """`tc qdisc show` of the robot's eth0 (side 'eth0') or of its port on the medium ('air')."""
    r = lab.robot(robot)
    ns, dev = (r.ns, naming.ROBOT_IFACE) if side == "eth0" else (naming.air_ns(lab.name), r.port)
    return kernel.run_in_ns(ns, ["tc", "qdisc", "show", "dev", dev], f"tc qdisc show dev {dev}")


def snmp(lab: Lab, robot: str, proto: str, counter: str) -> int:
    """A counter of /proc/net/snmp in the robot's namespace, e.g. ('Udp', 'InCsumErrors')."""
    lines = [ln.split() for ln in lab.exec(robot, ["cat", "/proc/net/snmp"]).stdout.splitlines()]
    names, values = (ln for ln in lines if ln and ln[0] == f"{proto}:")
    return int(values[names.index(counter)])


# -- fixtures ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Lab]:
    """Robots r1 and r2 on one medium; only r1's link is ever shaped."""
    caps = capabilities()
    if not caps.netem:
        pytest.skip(
            f"needs tc netem: {caps.why.get('netem', 'missing')}; "
            "`make test-netem` runs this tier in a VM with a Debian kernel"
        )
    with Lab(lab_name(), workdir=Path(tmp_path_factory.mktemp("netem"))) as lab:
        lab.add_robots(["r1", "r2"])
        yield lab


@pytest.fixture(scope="module")
def ends(lab: Lab) -> Iterator[dict[str, Endpoint]]:
    eps = {r: Endpoint(lab, r) for r in ("r1", "r2")}
    yield eps
    for ep in eps.values():
        ep.close()


@pytest.fixture(scope="module")
def baseline(lab: Lab) -> list[float]:
    """Round trips r1 -> r2 with no shaping (after one ping that resolves ARP)."""
    rtts(lab, "r1", "r2", count=1)
    return rtts(lab, "r1", "r2", count=20, interval=0.05)


@pytest.fixture(autouse=True)
def unshaped(lab: Lab) -> Iterator[None]:
    """Every test starts and ends with r1 unshaped, whatever it did."""
    lab.shape("r1")
    yield
    if lab.is_up:
        lab.shape("r1")


# -- tests -------------------------------------------------------------------------------------


def test_netem_sits_on_both_ends_of_the_link_and_goes_on_reset(lab: Lab) -> None:
    assert capabilities().netem
    lab.shape("r1", delay=50, loss=30)
    for side in ("eth0", "air"):
        shown = qdisc(lab, "r1", side)
        assert "netem" in shown and "delay 50ms" in shown and "loss 30%" in shown, (side, shown)
    assert "netem" not in qdisc(lab, "r2", "eth0") + qdisc(lab, "r2", "air")
    # With netem, link loss is the qdisc's, not a medium rule; the ground truth still has it.
    assert "numgen" not in lab.medium.rules()
    assert lab.links()[("r1", "r2")] == 30 and lab.links()[("r2", "r1")] == 30
    # A new shape replaces the old one whole: no delay left over.
    lab.shape("r1", loss=10)
    shown = qdisc(lab, "r1", "eth0")
    assert "loss 10%" in shown and "delay" not in shown, shown
    lab.shape("r1")
    for side in ("eth0", "air"):
        assert "netem" not in qdisc(lab, "r1", side)
    assert lab.shape_of("r1").is_none and lab.links()[("r1", "r2")] == 0
    lab.shape("r1")  # resetting what is not shaped is fine


def test_delay_50ms_gives_a_100ms_round_trip_and_reset_restores_the_baseline(
    lab: Lab, baseline: list[float]
) -> None:
    base = statistics.median(baseline)
    lab.shape("r1", delay=50)
    there, back = rtts(lab, "r1", "r2"), rtts(lab, "r2", "r1")
    print(f"rtt unshaped median {base:.2f} ms (min {min(baseline):.2f}, max {max(baseline):.2f})")
    for way, got in (("r1->r2", there), ("r2->r1", back)):
        print(
            f"rtt {way} with delay 50 ms: median {statistics.median(got):.2f} ms, "
            f"min {min(got):.2f}, max {max(got):.2f}"
        )
        # Each packet waits 50 ms in netem on each of its two crossings of r1's link.
        assert min(got) >= 99.0, f"{way}: {got}"
        extra = statistics.median(got) - base
        assert 95 <= extra <= 150, f"{way}: {extra:.1f} ms over the baseline {base:.2f} ms"
    lab.shape("r1")
    after = rtts(lab, "r1", "r2", count=20, interval=0.05)
    print(f"rtt after reset: median {statistics.median(after):.2f} ms, max {max(after):.2f}")
    assert statistics.median(after) <= base + 10, (baseline, after)
    assert max(after) < 50, after  # no packet waited in a netem queue any more


def test_loss_30_loses_30_percent_one_way_in_each_direction_and_reset_loses_none(
    lab: Lab, ends: dict[str, Endpoint]
) -> None:
    r1, r2 = ends["r1"], ends["r2"]
    n = 500
    assert send(r1, r2, n).count == n  # the measurement itself loses nothing
    lab.shape("r1", loss=30)
    out, into = send(r1, r2, n), send(r2, r1, n)
    for way, got in (("r1->r2 (r1's eth0)", out), ("r2->r1 (r1's air port)", into)):
        lost = 1 - got.count / n
        print(f"loss 30 %: {way}: {got.count}/{n} arrived, {lost:.1%} lost")
        assert 0.20 <= lost <= 0.40, f"{way}: {lost:.1%} lost with 30 % configured"
        assert len(set(got.seqs)) == got.count  # lost, not duplicated
    lab.shape("r1")
    after = send(r1, r2, n)
    print(f"after reset: {after.count}/{n} arrived")
    assert after.count == n


def test_jitter_spreads_the_delay_within_its_bounds(lab: Lab, baseline: list[float]) -> None:
    lab.shape("r1", delay=50, jitter=20)
    got = rtts(lab, "r1", "r2", count=30, interval=0.05)
    print(
        f"rtt with delay 50 ms jitter 20 ms: min {min(got):.2f}, "
        f"median {statistics.median(got):.2f}, max {max(got):.2f} ms"
    )
    # Each crossing waits 50 +- 20 ms: a round trip 60-140 ms over the link's own time.
    assert min(got) >= 59.0, got
    assert max(got) <= 140 + max(baseline) + 40, got  # + slack for the emulated machine
    assert max(got) - min(got) >= 20, f"no jitter: {got}"


def test_duplicate_100_doubles_every_datagram_each_way(lab: Lab, ends: dict[str, Endpoint]) -> None:
    r1, r2 = ends["r1"], ends["r2"]
    lab.shape("r1", duplicate=100)
    for src, dst in ((r1, r2), (r2, r1)):
        got = send(src, dst, 100)
        print(f"duplicate 100 %: {src.robot}->{dst.robot}: 100 sent, {got.count} arrived")
        assert sorted(got.seqs) == sorted(list(range(100)) * 2)


def test_reorder_lets_datagrams_overtake_without_losing_any(
    lab: Lab, ends: dict[str, Endpoint]
) -> None:
    r1, r2 = ends["r1"], ends["r2"]
    lab.shape("r1", delay=20)
    in_order = send(r1, r2, 100, gap=0.001)
    assert in_order.seqs == list(range(100))  # a plain delay keeps the order
    lab.shape("r1", delay=20, reorder=50)
    got = send(r1, r2, 100, gap=0.001)
    overtaken = sum(1 for a, b in itertools.pairwise(got.seqs) if b < a)
    print(f"reorder 50 % (delay 20 ms): {got.count}/100 arrived, {overtaken} out of order")
    assert sorted(got.seqs) == list(range(100))
    assert overtaken >= 5, got.seqs


def test_corrupt_makes_the_receiver_drop_datagrams_by_checksum(
    lab: Lab, ends: dict[str, Endpoint]
) -> None:
    r1, r2 = ends["r1"], ends["r2"]
    before = snmp(lab, "r2", "Udp", "InCsumErrors") + snmp(lab, "r2", "Ip", "InHdrErrors")
    lab.shape("r1", corrupt=100)
    n = 200
    got = send(r1, r2, n)
    errors = snmp(lab, "r2", "Udp", "InCsumErrors") + snmp(lab, "r2", "Ip", "InHdrErrors") - before
    print(f"corrupt 100 %: {got.count}/{n} arrived, {errors} checksum errors at r2")
    # netem flips one bit of each frame; only flips in the Ethernet addresses pass the
    # receiver's checksums (about 1 in 6 frames of this size).
    assert got.count <= n // 2, got.count
    assert got.intact  # whatever arrived is exactly what was sent
    assert errors >= n // 2, errors


def test_rate_1mbit_paces_the_link(lab: Lab, ends: dict[str, Endpoint]) -> None:
    r1, r2 = ends["r1"], ends["r2"]
    size, n = 1000, 100  # 100 frames of 1042 bytes: 0.83 s at 1 Mbit/s
    lab.shape("r1", rate="1mbit")
    shaped = send(r1, r2, n, size=size, gap=0)
    lab.shape("r1")
    clean = send(r1, r2, n, size=size, gap=0)
    rate, free = shaped.mbit_per_s(size), clean.mbit_per_s(size)
    print(f"rate 1 Mbit/s: {shaped.count}/{n} arrived at {rate:.2f} Mbit/s; unshaped {free:.1f}")
    assert shaped.count == n  # queued, not dropped
    assert 0.8 <= rate <= 1.2, f"{rate:.2f} Mbit/s through a 1 Mbit/s link"
    # Unshaped, the (emulated) sender sets the pace, well above the limit.
    assert free >= 2 * rate, f"unshaped only {free:.1f} Mbit/s"
