"""netlab.airmedium's pure parts: hwsim's frame messages on bytes, 802.11 addresses, the
fate of a frame given the links and a seeded rng, and the links file (the medium itself
runs in the radio tier: tests/radio/test_radio_medium.py)."""

from __future__ import annotations

import random
import struct
from pathlib import Path

import pytest

from netlab import airmedium, hwsim
from netlab.airmedium import Fate, TxFrame, fate
from netlab.errors import NetlabError
from netlab.ranges import Topology, UnitDisc

A = bytes.fromhex("420000000100")  # hwsim addresses
B = bytes.fromhex("420000000200")
BROADCAST = b"\xff" * 6


def frame(addr1: bytes, addr2: bytes, fc: int = 0x08) -> bytes:
    """An 802.11 header (frame control `fc`: data by default) and a little payload."""
    return bytes([fc, 0]) + b"\0\0" + addr1 + addr2 + addr2 + b"\0\0" + b"payload"


def tx(addr1: bytes = BROADCAST, **kw: object) -> TxFrame:
    base: dict[str, object] = {
        "transmitter": A,
        "frame": frame(addr1, bytes.fromhex("020000000100")),
        "flags": airmedium.TX_CTL_REQ_TX_STATUS,
        "rates": ((0, 3), (1, 2), (-1, 0), (-1, 0)),
        "cookie": 2**40 + 7,
        "freq": 2412,
    }
    return TxFrame(**{**base, **kw})  # type: ignore[arg-type]


def test_a_frame_message_reads_back_through_netlink() -> None:
    sent = tx(rate_flags=b"\x01\x00" * 4)
    raw = hwsim.encode(30, hwsim.CMD_FRAME, airmedium.tx_payload(sent), seq=0, flags=0)
    (msg,) = hwsim.decode(raw)
    assert msg.cmd == hwsim.CMD_FRAME
    assert airmedium.parse_tx(msg.attributes) == sent


def test_a_frame_message_without_its_cookie_or_frame_is_refused_by_name() -> None:
    attributes = dict(hwsim.attrs(airmedium.tx_payload(tx())))
    del attributes[hwsim.ATTR_COOKIE], attributes[hwsim.ATTR_FRAME]
    with pytest.raises(ValueError, match="without frame, cookie"):
        airmedium.parse_tx(attributes)


def test_a_delivery_names_the_receiver_with_a_signed_signal_and_the_frequency() -> None:
    sent = tx()
    got = dict(hwsim.attrs(airmedium.rx_payload(B, sent, rate=1)))
    assert got[hwsim.ATTR_ADDR_RECEIVER] == B
    assert got[hwsim.ATTR_FRAME] == sent.frame
    assert struct.unpack("=I", got[hwsim.ATTR_RX_RATE]) == (1,)
    assert struct.unpack("=i", got[hwsim.ATTR_SIGNAL]) == (airmedium.SIGNAL,)
    assert struct.unpack("=I", got[hwsim.ATTR_FREQ]) == (2412,)


@pytest.mark.parametrize(("sent", "told"), [(0, 0), (3, 3), (7, 7), (8, 0), (15, 0), (-1, 0)])
def test_a_receiver_is_told_a_rate_index_its_band_has(sent: int, told: int) -> None:
    """mac80211 drops a received frame whose legacy rate index is past its band's table:
    an HT sender's MCS 15 must not reach it as legacy rate 15."""
    got = dict(hwsim.attrs(airmedium.rx_payload(B, tx(), rate=sent)))
    assert struct.unpack("=I", got[hwsim.ATTR_RX_RATE]) == (told,)


@pytest.mark.parametrize("acked", [True, False])
def test_a_tx_status_carries_the_cookie_the_attempts_and_the_ack(acked: bool) -> None:
    sent = tx(flags=airmedium.TX_CTL_REQ_TX_STATUS | airmedium.TX_STAT_ACK)
    got = dict(hwsim.attrs(airmedium.status_payload(sent, acked, ((0, 3), (1, 1)))))
    assert got[hwsim.ATTR_ADDR_TRANSMITTER] == A
    assert struct.unpack("=Q", got[hwsim.ATTR_COOKIE]) == (sent.cookie,)
    flags = struct.unpack("=I", got[hwsim.ATTR_FLAGS])[0]
    assert bool(flags & airmedium.TX_STAT_ACK) is acked
    assert flags & airmedium.TX_CTL_REQ_TX_STATUS
    assert airmedium.parse_rates(got[hwsim.ATTR_TX_INFO]) == ((0, 3), (1, 1), (-1, 0), (-1, 0))
    assert hwsim.ATTR_SIGNAL in got  # the kernel ignores a status without one


def test_addresses_of_an_80211_header() -> None:
    data = frame(BROADCAST, bytes.fromhex("020000000300"))
    assert airmedium.address1(data) == BROADCAST and airmedium.is_group(BROADCAST)
    assert airmedium.address2(data) == bytes.fromhex("020000000300")
    assert not airmedium.is_group(bytes.fromhex("020000000300"))
    assert airmedium.is_group(bytes.fromhex("333300000001"))  # IPv6 multicast
    assert airmedium.address2(frame(A, B, fc=0xB4)) is None  # RTS: a control frame
    assert airmedium.address1(b"\x08\x00") is None


def test_the_hwsim_address_is_the_permanent_one_with_the_0x40_bit() -> None:
    assert hwsim.hwsim_address("02:00:00:00:0a:00") == "42:00:00:00:0a:00"
    assert airmedium.perm_address("42:00:00:00:0a:00") == "02:00:00:00:0a:00"
    with pytest.raises(ValueError, match="not a MAC address"):
        airmedium.mac_bytes("02:00:00:00:0a")
    with pytest.raises(NetlabError, match="not a MAC address"):
        hwsim.hwsim_address("zz:00:00:00:00:00")


def three(far: bool = False) -> Topology:
    topo = Topology(UnitDisc(10.0))
    topo.add("r1", (0.0, 0.0))
    topo.add("r2", (5.0, 0.0))
    topo.add("r3", (50.0 if far else 8.0, 0.0))
    return topo


ROBOTS = ("r1", "r2", "r3")
RATES = ((0, 3), (1, 2), (-1, 0), (-1, 0))


def test_a_group_frame_reaches_every_linked_radio_once_and_is_never_acked() -> None:
    rng = random.Random(1)
    near = fate("r1", None, True, RATES, three().links(), ROBOTS, rng)
    assert near == Fate((("r2", 0), ("r3", 0)), False, ((0, 1),))
    far = fate("r1", None, True, RATES, three(far=True).links(), ROBOTS, rng)
    assert far.receivers == (("r2", 0),)
    topo = three()
    topo.partition([["r1"], ["r2", "r3"]])
    assert fate("r1", None, True, RATES, topo.links(), ROBOTS, rng).receivers == ()


def test_a_clean_unicast_frame_is_acked_at_the_first_attempt() -> None:
    got = fate("r1", "r2", False, RATES, three().links(), ROBOTS, random.Random(1))
    assert got == Fate((("r2", 0),), True, ((0, 1),))


def test_a_unicast_frame_out_of_range_uses_every_attempt_and_reaches_no_one() -> None:
    got = fate("r1", "r3", False, RATES, three(far=True).links(), ROBOTS, random.Random(1))
    assert got == Fate((), False, ((0, 3), (1, 2)))


def test_without_the_reverse_link_the_frame_arrives_once_but_is_never_acked() -> None:
    topo = three()
    topo.set_pair_quality("r2", "r1", 100.0, both=False)
    got = fate("r1", "r2", False, RATES, topo.links(), ROBOTS, random.Random(1))
    assert got == Fate((("r2", 0),), False, ((0, 3), (1, 2)))


def test_a_frame_of_an_unknown_radio_or_to_an_unknown_one_reaches_no_one() -> None:
    links = three().links()
    assert fate(None, "r2", False, RATES, links, ROBOTS, random.Random(1)) == Fate(
        (), False, ((0, 1),)
    )
    assert fate("r1", None, False, RATES, links, ROBOTS, random.Random(1)) == Fate(
        (), False, ((0, 3), (1, 2))
    )


def test_loss_drops_group_frames_at_its_rate_and_costs_unicast_retries() -> None:
    topo = three()
    topo.set_pair_quality("r1", "r2", 40.0)
    links, rng = topo.links(), random.Random(7)
    n = 4000
    heard = sum(
        ("r2", 0) in fate("r1", None, True, RATES, links, ROBOTS, rng).receivers for _ in range(n)
    )
    assert 0.56 < heard / n < 0.64  # 60 % kept, within ~5 standard deviations
    fates = [fate("r1", "r2", False, RATES, links, ROBOTS, rng) for _ in range(n)]
    attempts = [sum(count for _, count in f.used) for f in fates]
    # An attempt succeeds when the frame and its ACK both pass: 0.6 * 0.6 = 0.36.
    assert 2.0 < sum(attempts) / n < 2.6
    lost = sum(not f.acked for f in fates) / n
    assert 0.08 < lost < 0.13  # 0.64 ** 5 = 0.107 of frames exhaust the five attempts
    assert all(f.receivers in ((), (("r2", 0),), (("r2", 1),)) for f in fates)
    assert max(attempts) == 5


def test_the_links_file_is_replaced_whole_and_reads_back(tmp_path: Path) -> None:
    path = tmp_path / "links.json"
    radios = {"r1": "42:00:00:00:01:00", "r2": "42:00:00:00:02:00"}
    airmedium.write_links(path, radios, {("r1", "r2"): 0.0, ("r2", "r1"): 12.5})
    table = airmedium.read_links(path)
    assert table.radios == {A: "r1", B: "r2"}
    assert table.links == {("r1", "r2"): 0.0, ("r2", "r1"): 12.5}
    assert [p.name for p in tmp_path.iterdir()] == ["links.json"]  # no temporary left
    path.write_text('{"radios": {"r1": "42:00"}, "links": []}')
    with pytest.raises(NetlabError, match=r"links file .*not a MAC address"):
        airmedium.read_links(path)


def test_a_wake_up_reads_every_frame_waiting_and_counts_how_far_behind_it_was(
    tmp_path: Path,
) -> None:
    """The medium drains its socket at each wake-up (at most BATCH datagrams) without
    blocking; a wake-up that finds more than one waiting counts as behind.  (A datagram
    socket pair stands in for the netlink socket: the kernel's side is the radio tier's.)"""
    import socket

    ours, kernel = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)

    class Genl:
        family = 30
        sock = ours

    medium = airmedium.Medium(Genl(), tmp_path / "links.json", tmp_path / "stats.json", 1)  # type: ignore[arg-type]
    try:
        for i in range(3):
            kernel.send(b"datagram %d" % i)
        assert medium.read() == [b"datagram 0", b"datagram 1", b"datagram 2"]
        assert medium.read() == []  # nothing waiting: no block
        for _ in range(airmedium.BATCH + 5):
            kernel.send(b"x")
        assert len(medium.read()) == airmedium.BATCH and len(medium.read()) == 5
        frames = [hwsim.encode(30, hwsim.CMD_FRAME, airmedium.tx_payload(tx()), 0, 0)] * 2
        medium.take([hwsim.encode(30, 99, b"", 0, 0), *frames])  # not a frame: skipped
        medium.take(frames[:1])
        counts = medium.counts
        assert (counts["frames"], counts["wakeups"], counts["behind"]) == (3, 2, 1)
        assert counts["max_batch"] == 3 and counts["unknown_sender"] == 3  # no links read
        assert medium.stats()["priority"] == "normal"  # until main() asks for more
    finally:
        ours.close()
        kernel.close()
