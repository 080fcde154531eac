"""netlab capture analysis on synthetic pcaps (no root): the SDfR scapy layer, records,
per-robot/per-type/per-second figures, the paper's measure, Update counting and the report."""

from __future__ import annotations

import json
import random
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("scapy")
pytest.importorskip("matplotlib")

from scapy.layers.inet import IP, UDP
from scapy.layers.l2 import ARP, Ether
from scapy.utils import wrpcap

from netlab import analysis, paper, pcap
from netlab.capture import (
    Capture,
    CaptureError,
    CaptureInfo,
    _parse_stats,
    sidecar_path,
)
from netlab.pcap import PcapError, Record
from netlab.report import write_report
from netlab.samples import AgreementSample, ConnectivitySample
from netlab.sdfr_layer import SDfR, describe
from sdfr import wire
from sdfr.protocol import auth
from sdfr.records.model import Service

GROUP = wire.DEFAULT_GROUP
T0 = 1_700_000_000.0
ROBOTS = (1, 2, 3)


def mac(i: int) -> str:
    return f"02:00:00:00:00:{i:02x}"


def ip(i: int) -> str:
    return f"10.1.0.{i}"


def origin(i: int, version: int = 1) -> wire.Origin:
    return wire.Origin(1, f"r{i}", 100 + i, version, f"{i:016x}")


def location(i: int) -> str:
    return f"http://{ip(i)}:8700/description.json"


def frame(src: int, dst: int | None, data: bytes, t: float, sport: int = 1900) -> Ether:
    """An Ethernet frame from robot `src` to robot `dst` (None: the multicast group)."""
    if dst is None:
        eth = Ether(src=mac(src), dst="01:00:5e:7f:ff:fa")
        pkt = eth / IP(src=ip(src), dst=GROUP, ttl=2) / UDP(sport=sport, dport=1900) / data
    else:
        eth = Ether(src=mac(src), dst=mac(dst))
        pkt = eth / IP(src=ip(src), dst=ip(dst)) / UDP(sport=sport, dport=1900) / data
    pkt = Ether(bytes(pkt))
    pkt.time = t
    return pkt


SERVICES = tuple(
    Service(f"s{k}", f"service number {k} " + "x" * 100, "sensor.camera", attributes={"k": k})
    for k in range(20)
)
#: Update datagrams the service set above takes (more than one: the split is exercised).
PARTS = len(wire.encode_update_parts(origin(1, 2), location(1), 30, SERVICES))


def scenario() -> list[tuple[int, int | None, bytes, float]]:
    """(sender, unicast receiver or None, datagram, time offset) for a 3-robot run."""
    out: list[tuple[int, int | None, bytes, float]] = []
    for i in ROBOTS:  # beacons every 0.5 s for 3 s, staggered
        for k in range(6):
            out.append(
                (i, None, wire.encode(wire.Alive(origin(i), location(i), 30)), k * 0.5 + i / 10)
            )
    # r2 starts with a search; r1 and r3 answer by unicast
    search = wire.Discovery(origin(2), wire.fleet_target(1), 1, want=wire.WANT_ALL)
    out.append((2, None, wire.encode(search), 0.05))
    for i in (1, 3):
        resp = wire.Response(origin(i), wire.fleet_target(1), location(i), 30)
        out.append((i, 2, wire.encode(resp), 0.08))
    # r1 publishes: a multi-part Update at 1.2 s
    parts = wire.encode_update_parts(origin(1, 2), location(1), 30, SERVICES)
    out.extend((1, None, p, 1.2) for p in parts)
    # a unicast ping r3 -> r1 and its reply
    ping = wire.Discovery(origin(3), "uuid:r1", 0, seq=7, multicast=False)
    out.append((3, 1, wire.encode(ping, group=ip(1)), 1.5))
    out.append(
        (1, 3, wire.encode(wire.Response(origin(1), "uuid:r1", location(1), 30, seq=7)), 1.51)
    )
    # junk from r2, a plain SSDP search (no SDfR headers) from r3, r3 leaves at 2.9 s
    out.append((2, None, b"GET / HTTP/1.0\r\n\r\n", 2.0))
    plain = wire.Discovery(None, "ssdp:all", 1)
    out.append((3, None, wire.encode(plain), 2.1))
    out.append((3, None, wire.encode(wire.Byebye(origin(3))), 2.9))
    return sorted(out, key=lambda x: x[3])


def arp_frames() -> list[tuple[int, Ether]]:
    probe = Ether(src=mac(1), dst="ff:ff:ff:ff:ff:ff") / ARP(
        op=1, hwsrc=mac(1), psrc="0.0.0.0", pdst=ip(1)
    )
    announce = Ether(src=mac(1), dst="ff:ff:ff:ff:ff:ff") / ARP(
        op=1, hwsrc=mac(1), psrc=ip(1), pdst=ip(1)
    )
    request = Ether(src=mac(2), dst="ff:ff:ff:ff:ff:ff") / ARP(
        op=1, hwsrc=mac(2), psrc=ip(2), pdst=ip(3)
    )
    reply = Ether(src=mac(3), dst=mac(2)) / ARP(op=2, hwsrc=mac(3), psrc=ip(3), pdst=ip(2))
    out = []
    for k, (sender, pkt) in enumerate([(1, probe), (1, announce), (2, request), (3, reply)]):
        pkt = Ether(bytes(pkt))
        pkt.time = T0 + 0.01 + k * 0.001
        out.append((sender, pkt))
    return out


def write_sidecar(pcap: Path, label: str, role: str, own: str | None) -> None:
    info = CaptureInfo(None, "eth0" if role == "robot" else "br0", label, role, own, [], "", 2048)
    sidecar_path(pcap).write_text(json.dumps(info.to_json()))


@pytest.fixture
def run(tmp_path: Path) -> dict[str, Any]:
    """Robot captures r1..r3 (with sidecars) and a medium capture air.pcap, plus the expected
    figures computed straight from the scenario."""
    robot_frames: dict[int, list[Ether]] = {i: [] for i in ROBOTS}
    medium: list[Ether] = []
    expect: dict[str, Any] = {
        "tx": {f"r{i}": [0, 0, 0] for i in ROBOTS},  # datagrams, payload, frame
        "rx": {f"r{i}": [0, 0, 0] for i in ROBOTS},
        "types": {},
    }
    for sender, dst, data, dt in scenario():
        pkt = frame(sender, dst, data, T0 + dt)
        medium.append(pkt)
        robot_frames[sender].append(pkt)
        size = (1, len(data), len(pkt))
        tx = expect["tx"][f"r{sender}"]
        for k in range(3):
            tx[k] += size[k]
        for i in ROBOTS:
            if i != sender and (dst is None or dst == i):
                robot_frames[i].append(pkt)
                rx = expect["rx"][f"r{i}"]
                for k in range(3):
                    rx[k] += size[k]
    for _sender, pkt in arp_frames():
        medium.append(pkt)
        for i in ROBOTS:
            robot_frames[i].append(pkt)
    paths = {}
    for i in ROBOTS:
        path = tmp_path / f"r{i}.pcap"
        wrpcap(str(path), sorted(robot_frames[i], key=lambda p: float(p.time)))
        write_sidecar(path, f"r{i}", "robot", mac(i))
        paths[f"r{i}"] = path
    air = tmp_path / "air.pcap"
    wrpcap(str(air), sorted(medium, key=lambda p: float(p.time)))
    write_sidecar(air, "air", "medium", None)
    paths["air"] = air
    return {"dir": tmp_path, "paths": paths, "expect": expect}


# -- the scapy layer ------------------------------------------------------------------------


def test_layer_dissects_every_message_type() -> None:
    alive = frame(1, None, wire.encode(wire.Alive(origin(1, 5), location(1), 30)), T0)
    layer = alive[SDfR]
    assert (layer.method, layer.msg_type, layer.robot, layer.fleet) == ("NOTIFY", "Alive", "r1", 1)
    assert (layer.boot, layer.version, layer.part, layer.services) == (101, 5, None, None)
    assert layer.start == "NOTIFY * HTTP/1.1"
    assert alive[UDP].load == layer.load == bytes(layer)
    assert "SDfR Alive r1 fleet=1 boot=101 v=5" in alive.summary()

    parts = wire.encode_update_parts(origin(2, 9), location(2), 30, SERVICES)
    assert len(parts) == PARTS > 1
    got = [SDfR(p) for p in parts]
    assert [(u.msg_type, u.part, u.parts) for u in got] == [
        ("Update", k, PARTS) for k in range(PARTS)
    ]
    assert sum(u.services for u in got) == len(SERVICES)
    assert f"part 2/{PARTS}" in got[1].mysummary()

    search = SDfR(wire.encode(wire.Discovery(origin(3), "ssdp:all", 2)))
    assert (search.method, search.msg_type, search.st, search.seq) == (
        "M-SEARCH",
        "Discovery",
        "ssdp:all",
        None,
    )
    ping = SDfR(
        wire.encode(wire.Discovery(origin(3), "uuid:r1", 0, seq=4, multicast=False), group=ip(1))
    )
    assert ping.seq == 4 and "(ping)" in ping.mysummary()
    resp = SDfR(wire.encode(wire.Response(origin(1), "uuid:r1", location(1), 30, seq=4)))
    assert (resp.method, resp.msg_type, resp.seq) == ("RESPONSE", "Response", 4)
    bye = SDfR(wire.encode(wire.Byebye(origin(2))))
    assert (bye.msg_type, bye.robot) == ("Byebye", "r2")
    plain = SDfR(wire.encode(wire.Discovery(None, "ssdp:all", 1)))
    assert (plain.msg_type, plain.robot) == ("Discovery", None)
    assert (alive[SDfR].key, alive[SDfR].counter) == (None, None)


def test_layer_shows_the_seal_of_a_keyed_fleet() -> None:
    key = bytes(range(32))
    sealed = auth.seal(wire.encode(wire.Alive(origin(1, 5), location(1), 30)), key, 77)
    layer = SDfR(sealed)
    assert (layer.msg_type, layer.robot, layer.key, layer.counter) == (
        "Alive",
        "r1",
        auth.key_id(key),
        77,
    )


def test_layer_binds_to_port_1900_both_ways() -> None:
    data = wire.encode(wire.Response(origin(1), "ssdp:all", location(1), 30))
    reply = Ether(bytes(Ether() / IP() / UDP(sport=1900, dport=40000) / data))
    assert reply[SDfR].msg_type == "Response"
    other = Ether(bytes(Ether() / IP() / UDP(sport=40000, dport=53) / data))
    assert SDfR not in other


@pytest.mark.parametrize(
    ("data", "reason"),
    [
        (b"GET / HTTP/1.0\r\n\r\n", "bad-start-line"),
        (b"", "bad-start-line"),
        (b"\xff\xfe\x00garbage", "bad-start-line"),
        (b"NOTIFY * HTTP/1.1\r\nNTS: ssdp:alive\r\nbroken line\r\n\r\n", "bad-header"),
        (b"NOTIFY * HTTP/1.1\r\nNT: x\r\nNTS: ssdp:alive\r\n\r\n", "not-sdfr"),
        (b"X" * 1500, "too-large"),
    ],
)
def test_malformed_datagram_dissects_as_reject(data: bytes, reason: str) -> None:
    pkt = Ether(bytes(Ether() / IP() / UDP(sport=1900, dport=1900) / data))
    if not data:
        assert describe(data)["reason"] == reason
        return
    layer = pkt[SDfR]
    assert (layer.msg_type, layer.reason) == ("Reject", reason)
    assert layer.detail
    assert "SDfR Reject " + reason in layer.mysummary()


def test_dissection_never_raises() -> None:
    rng = random.Random(1900)
    valid = [wire.encode(wire.Alive(origin(1), location(1), 30))]
    valid += wire.encode_update_parts(origin(1), location(1), 30, SERVICES)
    for _ in range(300):
        base = rng.choice(valid)
        cut = base[: rng.randrange(len(base) + 1)]
        flipped = bytearray(cut)
        for _ in range(rng.randrange(4)):
            if flipped:
                flipped[rng.randrange(len(flipped))] = rng.randrange(256)
        layer = SDfR(bytes(flipped))
        assert layer.msg_type in ("Alive", "Update", "Reject")
        assert isinstance(layer.summary(), str)


# -- records ----------------------------------------------------------------------------------


def test_records_carry_direction_sizes_and_sdfr_fields(run: dict[str, Any]) -> None:
    recs = list(pcap.read_pcap(run["paths"]["r1"]))
    assert {r.capture for r in recs} == {"r1"}
    sdfr_recs = [r for r in recs if r.kind == "sdfr"]
    alive = next(r for r in sdfr_recs if r.msg_type == "Alive" and r.robot == "r1")
    assert alive.direction == "tx" and alive.multicast and alive.dst == GROUP
    assert alive.payload_len == len(wire.encode(wire.Alive(origin(1), location(1), 30)))
    assert alive.frame_len == alive.payload_len + 14 + 20 + 8
    assert alive.time == pytest.approx(T0 + 0.1)
    assert (alive.fleet, alive.boot, alive.version) == (1, 101, 1)
    other = next(r for r in sdfr_recs if r.robot == "r2")
    assert other.direction == "rx"
    update = [r for r in sdfr_recs if r.msg_type == "Update"]
    assert [(r.part, r.parts) for r in update] == [(k, PARTS) for k in range(PARTS)]
    junk = [r for r in recs if r.msg_type == "Reject"]
    assert len(junk) == 1 and junk[0].reason == "bad-start-line" and junk[0].robot is None
    arp = [r for r in recs if r.kind == "arp"]
    assert len(arp) == 4 and arp[0].msg_type == "ARP"
    # the medium has no direction
    air = list(pcap.read_pcap(run["paths"]["air"]))
    assert {r.direction for r in air} == {""}
    # overrides win over the sidecar
    relabelled = list(pcap.read_pcap(run["paths"]["r1"], label="x", own_mac=mac(2)))
    assert {r.capture for r in relabelled} == {"x"}
    assert next(r for r in relabelled if r.robot == "r2").direction == "tx"


def test_sent_and_received_per_robot(run: dict[str, Any]) -> None:
    recs = pcap.read_run(run["dir"])
    assert [r.time for r in recs] == sorted(r.time for r in recs)
    expect = run["expect"]
    sent = analysis.sent_per_robot(recs)
    got = {k: [v.datagrams, v.payload_bytes, v.frame_bytes] for k, v in sent.items()}
    assert got == expect["tx"]
    received = analysis.received_per_robot(recs)
    got = {k: [v.datagrams, v.payload_bytes, v.frame_bytes] for k, v in received.items()}
    assert got == expect["rx"]
    # the medium alone gives the same TX
    air = list(pcap.read_pcap(run["paths"]["air"]))
    medium_sent = {k: v.to_json() for k, v in analysis.sent_per_robot(air).items()}
    assert medium_sent == {k: v.to_json() for k, v in sent.items()}
    assert analysis.capture_owners(recs) == {"r1": "r1", "r2": "r2", "r3": "r3"}
    traffic = analysis.traffic_per_robot(recs)
    assert list(traffic) == ["r1", "r2", "r3"]
    assert traffic["r2"].rx.datagrams == expect["rx"]["r2"][0]


def test_per_type_rejects_and_updates(run: dict[str, Any]) -> None:
    recs = pcap.read_run(run["dir"])
    types = {k: v.datagrams for k, v in analysis.per_type(recs).items()}
    assert types == {
        "Alive": 18,
        "Byebye": 1,
        "Discovery": 2,
        "Ping": 1,
        "Ping reply": 1,
        "Reject": 1,
        "Response": 2,
        "Update": PARTS,
    }
    merged = {k: v.datagrams for k, v in analysis.per_type(recs, split_pings=False).items()}
    assert merged["Discovery"] == 3 and merged["Response"] == 3
    alive_bytes = analysis.per_type(recs)["Alive"].payload_bytes
    assert alive_bytes == sum(len(d) for _, _, d, _ in scenario() if b"ssdp:alive" in d)
    assert analysis.rejects(recs) == {"bad-start-line": 1}

    assert analysis.count_updates(recs) == PARTS
    assert analysis.count_updates(recs, since=T0 + 1.2) == PARTS
    assert analysis.count_updates(recs, since=T0 + 1.21) == 0
    assert analysis.count_updates(recs, until=T0 + 1.2) == 0
    assert analysis.count_updates(recs, robot="r2") == 0
    # each datagram once, whichever captures are given
    assert analysis.count_updates(pcap.read_run(run["paths"]["air"])) == PARTS


def test_per_second_series(run: dict[str, Any]) -> None:
    recs = pcap.read_run(run["dir"])
    by_type = analysis.per_second(recs, by="type", start=T0)
    assert by_type.step == 1.0 and by_type.bins == 3 and by_type.times == [0.0, 1.0, 2.0]
    assert by_type.values["Alive"] == [6.0, 6.0, 6.0]
    assert by_type.values["Update"] == [0.0, PARTS, 0.0]
    assert by_type.values["Byebye"] == [0.0, 0.0, 1.0]
    total = analysis.per_second(recs, by="total", start=T0)
    assert sum(total.values["total"]) == 26 + PARTS
    by_robot = analysis.per_second(recs, by="robot", value="payload_bytes", start=T0)
    assert sum(by_robot.values["r1"]) == run["expect"]["tx"]["r1"][1]
    half = analysis.per_second(recs, by="receiver", step=0.5, start=T0, end=T0 + 2.99)
    assert half.bins == 6
    assert sum(half.values["r2"]) == run["expect"]["rx"]["r2"][0]
    with pytest.raises(ValueError):
        analysis.per_second(recs, by="colour")
    with pytest.raises(ValueError):
        analysis.per_second(recs, value="bits")


def test_paper_measure_states_both_sizes(run: dict[str, Any]) -> None:
    recs = pcap.read_run(run["dir"])
    m = paper.paper_measure(recs, duration=3.0)
    r1 = m["robots"]["r1"]
    tx = run["expect"]["tx"]["r1"]
    assert r1["tx"] == {"datagrams": tx[0], "payload_bytes": tx[1], "frame_bytes": tx[2]}
    assert r1["tx_kB"]["payload"] == pytest.approx(tx[1] / 1000)
    assert r1["tx_kB"]["frame"] == pytest.approx(tx[2] / 1000)
    assert r1["per_5_min_kB"]["tx_payload"] == pytest.approx(tx[1] / 1000 * 100, rel=1e-3)
    assert "UDP payload" in m["definition"] and "Ethernet frame" in m["definition"]
    assert m["paper_5_min_kB"] == {"tx": [220, 320], "rx": [540, 850]}
    assert m["duration_s"] == 3.0


def test_arp_counts(run: dict[str, Any]) -> None:
    recs = pcap.read_run(run["dir"])
    counts = analysis.arp_counts(recs)
    assert counts.to_json() == {"probes": 1, "announcements": 1, "requests": 1, "replies": 1}
    per = analysis.arp_counts_by_sender(recs)
    assert per[mac(1)].probes == 1 and per[mac(1)].announcements == 1
    assert per[mac(3)].replies == 1


def test_records_without_metadata_count_once_per_capture(tmp_path: Path) -> None:
    data = wire.encode(wire.Alive(origin(1), location(1), 30))
    path = tmp_path / "bare.pcap"
    wrpcap(str(path), [frame(1, None, data, T0 + k) for k in range(4)])
    recs = pcap.read_run(path)
    assert {r.direction for r in recs} == {""} and {r.capture for r in recs} == {"bare"}
    assert analysis.sent_per_robot(recs)["r1"].datagrams == 4
    assert analysis.received_per_robot(recs) == {}


def test_unreadable_pcaps(tmp_path: Path) -> None:
    empty = tmp_path / "empty.pcap"
    empty.write_bytes(b"")
    assert list(pcap.read_pcap(empty)) == []
    bogus = tmp_path / "bogus.pcap"
    bogus.write_bytes(b"this is not a pcap file at all")
    with pytest.raises(PcapError, match="not a pcap"):
        list(pcap.read_pcap(bogus))
    with pytest.raises(PcapError, match="cannot read"):
        list(pcap.read_pcap(tmp_path / "missing.pcap"))
    # a header with no packets (tcpdump stopped before anything arrived)
    header_only = tmp_path / "header.pcap"
    header_only.write_bytes(struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 2048, 1))
    assert list(pcap.read_pcap(header_only)) == []


def test_ethernet_frames_read_from_their_headers_are_what_scapy_dissects(tmp_path: Path) -> None:
    """An Ethernet capture's records come from the frames' headers read directly (scapy took a
    millisecond a frame, fifty times that in the emulated VM): for every kind of frame, the
    same records as scapy's dissection, which still reads what the headers leave to it."""
    from scapy.layers.inet import ICMP, TCP, IPOption_RR
    from scapy.layers.inet6 import IPv6
    from scapy.layers.l2 import LLC, Dot1Q
    from scapy.packet import Raw
    from scapy.utils import PcapReader, PcapWriter

    alive = wire.encode(wire.Alive(origin(1), location(1), 30))
    eth = Ether(src=mac(1), dst=mac(2))
    extra = [
        eth / IP(src=ip(1), dst=ip(2)) / TCP(sport=1234, dport=8700) / b"GET /",
        eth / IP(src=ip(1), dst=GROUP, proto=2) / Raw(b"\x16\x00\xfa\x04" + bytes(4)),  # IGMP
        eth / IP(src=ip(1), dst=ip(2)) / UDP(sport=5353, dport=5353) / b"mdns",
        eth / IP(src=ip(1), dst=ip(2)) / UDP(sport=40000, dport=1900) / b"",  # empty
        eth / IP(src=ip(1), dst=ip(2), options=[IPOption_RR()]) / UDP(dport=1900) / alive,
        eth / IP(src=ip(1), dst=ip(2)) / UDP(sport=1900, dport=1900, len=20) / alive,  # short len
        eth / IP(src=ip(1), dst=ip(2)) / ICMP() / IP(src=ip(2), dst=ip(1)) / UDP(dport=1900),
        eth / IP(src=ip(1), dst=ip(2), flags="MF") / UDP(dport=1900) / alive,  # a fragment
        eth
        / IP(src=ip(1), dst=ip(2), frag=10, proto=17)
        / Raw(struct.pack("!HHHH", 1900, 1900, 48, 0) + alive[:40]),  # a later fragment
        eth / IPv6(src="fe80::1", dst="ff02::c") / UDP(sport=1900, dport=1900) / alive,
        eth / Dot1Q(vlan=5) / IP(src=ip(1), dst=ip(2)) / UDP(dport=1900) / alive,
        Ether(src=mac(1), dst=mac(2), type=60) / LLC() / Raw(b"x" * 40),  # 802.3 length
        Ether(src=mac(1), dst=mac(2), type=0x88B5) / Raw(b"x" * 50),
        Ether(src=mac(1), dst=mac(2)) / ARP(op=2, hwsrc=mac(1), psrc=ip(1), pdst=ip(2)),
    ]
    frames = [p for _s, p in arp_frames()]
    frames += [frame(s, d, data, T0 + dt) for s, d, data, dt in scenario()]
    frames += [Ether(bytes(f)) for f in extra]
    for i, f in enumerate(frames[-len(extra) :]):
        f.time = T0 + 5 + i / 10
    frames.append(Ether(bytes(frames[-1])[:30]))  # cut short by the snap length
    frames[-1].time, frames[-1].wirelen = T0 + 9, 60
    for nano in (False, True):
        path = tmp_path / f"eth-{nano}.pcap"
        with PcapWriter(str(path), nano=nano, linktype=1) as w:
            for f in frames:
                w.write(f)
        write_sidecar(path, "r1", "robot", mac(1))
        ours = list(pcap.read_pcap(path))
        with PcapReader(str(path)) as reader:
            theirs = [pcap._record(p, "r1", mac(1)) for p in reader]
        assert len(ours) == len(frames)
        assert ours == theirs
        kinds = [r.kind for r in ours[-len(extra) - 1 :]]
        assert kinds[:6] == [pcap.OTHER, pcap.OTHER, pcap.OTHER, pcap.SDFR, pcap.SDFR, pcap.SDFR]
    # A pcap cut off in a record (tcpdump killed) gives the records before the cut.
    whole = (tmp_path / "eth-False.pcap").read_bytes()
    cut = tmp_path / "cut.pcap"
    cut.write_bytes(whole[:-10])
    assert len(list(pcap.read_pcap(cut))) == len(frames) - 1


def test_importing_netlab_modules_does_not_import_scapy_or_matplotlib() -> None:
    code = (
        "import sys, netlab.analysis, netlab.pcap, netlab.paper, netlab.report, netlab.capture; "
        "print(sorted(m for m in ('scapy', 'matplotlib') if m in sys.modules))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60
    )
    assert out.stdout.strip() == "[]"


# -- report -----------------------------------------------------------------------------------


def is_png(path: Path) -> bool:
    return path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 5000


def test_report_writes_json_and_plots(run: dict[str, Any]) -> None:
    recs = pcap.read_run(run["dir"])
    conn = [
        ConnectivitySample(
            T0 + k,
            linked_pairs=3,
            reachable={"r1": 2, "r2": 2, "r3": min(2, k)},
            reachable_pairs=min(3, k + 1),
        )
        for k in range(4)
    ]
    agree: list[Any] = [{"time": T0 + k, "agreement": a} for k, a in enumerate([0.5, 0.9, 1.0])]
    agree.append(AgreementSample(T0 + 3, 1.0, per_robot={"r1": 1.0, "r2": 1.0, "r3": 1.0}))
    out_dir = run["dir"] / "report"
    report = write_report(
        out_dir,
        records=recs,
        connectivity_samples=conn,
        agreement_samples=agree,
        meta={"scenario": "synthetic", "start": T0, "duration_s": 3.0},
    )
    on_disk = json.loads((out_dir / "report.json").read_text())
    assert on_disk == report
    assert report["meta"]["scenario"] == "synthetic"
    assert report["window"] == {"start": T0, "end": T0 + 3.0, "duration_s": 3.0}
    assert report["traffic"]["robots"]["r1"]["tx"]["datagrams"] == run["expect"]["tx"]["r1"][0]
    assert report["per_type"]["Alive"]["datagrams"] == 18
    assert report["updates"] == PARTS and report["rejects"] == {"bad-start-line": 1}
    assert report["arp"]["probes"] == 1
    assert report["captures"]["r2"]["robot"] == "r2"
    assert report["captures"]["air"]["role"] == "unknown"  # the sidecars are elsewhere
    assert report["connectivity"]["linked_pairs"] == {"min": 3, "max": 3, "mean": 3.0}
    assert report["agreement"]["mean"] == pytest.approx(0.85)
    assert report["agreement"]["share_at_target"] == 0.5
    assert set(report["plots"]) == {
        "bytes_per_robot",
        "datagrams_per_type",
        "connectivity",
        "agreement",
    }
    for name in report["plots"].values():
        assert is_png(out_dir / name), name


def test_a_report_without_plots_is_the_same_json_and_no_png(run: dict[str, Any]) -> None:
    """`netlab run --no-plots` (for CI and the emulated VM tiers): report.json as with plots,
    but for its empty ``plots``, and no PNG drawn."""
    recs = pcap.read_run(run["dir"])
    meta = {"scenario": "synthetic", "start": T0, "duration_s": 3.0}
    with_plots = write_report(run["dir"] / "a", records=recs, meta=meta)
    without = write_report(run["dir"] / "b", records=recs, meta=meta, plots=False)
    assert without["plots"] == {} and with_plots["plots"]
    assert {**without, "plots": with_plots["plots"]} == with_plots
    assert not list((run["dir"] / "b").glob("*.png"))


def test_report_reads_the_run_dir_and_copes_with_nothing(
    run: dict[str, Any], tmp_path: Path
) -> None:
    report = write_report(run["dir"], records=None)
    assert report["captures"]["air"]["role"] == "medium"
    assert report["captures"]["r1"]["iface"] == "eth0"
    assert report["traffic"]["robots"]["r3"]["rx"]["datagrams"] == run["expect"]["rx"]["r3"][0]
    assert "connectivity" not in report and "agreement" not in report
    assert set(report["plots"]) == {"bytes_per_robot", "datagrams_per_type"}

    empty = write_report(tmp_path / "nothing", records=[])
    assert empty["traffic"]["robots"] == {} and empty["per_type"] == {}
    for name in empty["plots"].values():
        assert (tmp_path / "nothing" / name).exists()


def test_report_rejects_bad_samples(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="agreement"):
        write_report(tmp_path, records=[], agreement_samples=[{"time": 1.0, "agreement": 95}])


def test_record_json_round_trip() -> None:
    rec = Record(T0, "r1", "tx", "sdfr", mac(1), "", ip(1), GROUP, True, 421, 379)
    assert Record(**rec.to_json()) == rec


# -- capture errors that need no root -----------------------------------------------------------


def test_capture_reports_missing_tcpdump_and_interface(tmp_path: Path) -> None:
    with pytest.raises(CaptureError, match="no-such-tcpdump not found"):
        Capture(None, "lo", tmp_path / "x.pcap", tcpdump="no-such-tcpdump").start()
    with pytest.raises(CaptureError, match="no interface nope0"):
        Capture(None, "nope0", tmp_path / "x.pcap").start()
    with pytest.raises(CaptureError, match="never started"):
        Capture(None, "lo", tmp_path / "x.pcap").stop()
    with pytest.raises(ValueError):
        Capture(None, "a/b", tmp_path / "x.pcap")


def test_tcpdump_counters_are_parsed() -> None:
    lines = [
        "tcpdump: listening on eth0, link-type EN10MB (Ethernet), snapshot length 2048 bytes",
        "12 packets captured",
        "14 packets received by filter",
        "1 packet dropped by kernel",
    ]
    stats = _parse_stats(lines)
    assert (stats.captured, stats.received, stats.dropped) == (12, 14, 1)
    assert _parse_stats([]).captured is None


def test_ping_delivery_pairs_pings_with_their_replies() -> None:
    from netlab.analysis import PingTally, ping_delivery

    def rec(
        t: float, cap: str, d: str, src: int, dst: int, typ: str, seq: int, ping: int | None = None
    ) -> Record:
        return Record(
            t, cap, d, "sdfr", mac(src), mac(dst), ip(src), ip(dst), False, 300, 258,
            msg_type=typ, robot=f"r{src}", seq=seq, ping=ping,
        )  # fmt: skip

    recs = [
        # r1 pings r2 three times; replies 1 and 3 come back (reply 2 is lost).
        rec(T0 + 0, "r1", "tx", 1, 2, "Discovery", 1),
        rec(T0 + 0.01, "r1", "rx", 2, 1, "Response", 1),
        rec(T0 + 1, "r1", "tx", 1, 2, "Discovery", 2),
        rec(T0 + 2, "r1", "tx", 1, 2, "Discovery", 3),
        rec(T0 + 2.01, "r1", "rx", 2, 1, "Response", 3),
        # r2 pings r1 once, unanswered; its reply to r1's first ping carried another ping
        # of its own (8), which r1 answered.
        rec(T0 + 0.5, "r2", "tx", 2, 1, "Discovery", 7),
        rec(T0 + 0.01, "r2", "tx", 2, 1, "Response", 1, ping=8),
        rec(T0 + 0.02, "r2", "rx", 1, 2, "Response", 8),
    ]
    assert ping_delivery(recs) == {
        ("r1", "r2"): PingTally(3, 2),
        ("r2", "r1"): PingTally(2, 1),
    }
    assert ping_delivery(recs)[("r1", "r2")].rate == pytest.approx(2 / 3)
    assert ping_delivery(recs, since=T0 + 1) == {("r1", "r2"): PingTally(2, 1)}
    assert PingTally(0, 0).rate is None


def test_every_time_plot_of_a_run_shares_its_axis_events_deadlines_and_title() -> None:
    from netlab.plots import Timeline

    t0 = 1000.0
    meta = {
        "scenario": "split",
        "agreement_lag_s": 1.0,
        "agreement_target": 0.9,
        "steps": [
            {"step": 1, "kind": "start", "label": None, "start": t0 + 1, "end": t0 + 3},
            {"step": 2, "kind": "partition", "label": "split", "start": t0 + 4, "end": t0 + 4.5},
            {"step": 3, "kind": "check", "label": None, "start": t0 + 4.5, "end": t0 + 6},
            {"step": 4, "kind": "kill", "label": None, "start": t0 + 7, "end": t0 + 7.2},
            {"step": 5, "kind": "wait", "label": None, "start": t0 + 7.2, "end": t0 + 8},
        ],
        "checks": [
            {"step": 3, "description": "each side lists its side", "deadline_s": 3.5},
            {"step": 5, "description": "gone", "deadline_s": None},
        ],
    }
    tl = Timeline.of(meta, t0, t0 + 20, "split-20261124-1")
    assert tl.title == "split · run split-20261124-1" and tl.duration == 20.0
    assert [(t, label) for t, label, _ in tl.events] == [(4.0, "split"), (7.0, "kill -9")]
    # A deadline counts from the end of the last action before the check.
    assert tl.deadlines == ((8.0, "each side lists its side"),)
    assert (tl.lag, tl.target) == (1.0, 0.9)
    bare = Timeline.of({}, t0, t0 + 5, "pcaps")
    assert bare.title == "run pcaps" and bare.target is None and bare.events == ()


def _classic_pcap(path: Path, frames: list[tuple[float, bytes]], link: int = 1) -> None:
    import struct

    with path.open("wb") as f:
        f.write(struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, link))
        for t, data in frames:
            sec = int(t)
            f.write(struct.pack("<IIII", sec, round((t - sec) * 1e6), len(data), len(data)))
            f.write(data)


def test_pcaps_of_hosts_merge_on_one_clock_in_time_order(tmp_path: Path) -> None:
    """A lab across hosts merges its hosts' medium pcaps: each host's clock offset is taken
    off its frames' times, and the frames come out in time order, bytes untouched."""
    from netlab.pcap import PcapError, _frames, merge

    a, b = tmp_path / "a.pcap", tmp_path / "b.pcap"
    _classic_pcap(a, [(100.0, b"a1"), (102.0, b"a2")])
    _classic_pcap(b, [(100.5, b"b1"), (101.2, b"b2")])  # b's clock is 0.4 s ahead
    out = tmp_path / "medium.pcap"
    assert merge([(a, 0.0), (b, 0.4)], out) == 4
    got = [(data, round(t, 6)) for data, t, _ in _frames(out)]
    assert got == [(b"a1", 100.0), (b"b1", 100.1), (b"b2", 100.8), (b"a2", 102.0)]
    radio = tmp_path / "air.pcap"
    _classic_pcap(radio, [(1.0, b"x")], link=127)
    with pytest.raises(PcapError, match="link type 127, the others' 1: cannot merge"):
        merge([(a, 0.0), (radio, 0.0)], out)
