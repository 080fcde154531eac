"""Captures on the air: a radio lab's medium capture (hwsim0: radiotap + 802.11) read into the
same records as a wired one, with 802.11 management, control, EAPOL and encrypted data frames
counted apart, and what the air carried tallied per transmitter in the report.  Synthetic
pcaps built with scapy, as hwsim0 writes them; the radio tier captures the real thing."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from scapy.layers.dot11 import Dot11, Dot11Auth, Dot11Beacon, Dot11Elt, Dot11QoS, RadioTap
from scapy.layers.eap import EAPOL as EapolLayer
from scapy.layers.inet import IP, UDP
from scapy.layers.l2 import LLC, SNAP
from scapy.packet import Packet, Raw
from scapy.utils import wrpcap

from netlab import airmedium, hwsim
from netlab.analysis import AIR_KINDS, air_use
from netlab.capture import CaptureInfo, sidecar_path
from netlab.pcap import EAPOL, SDFR, WIFI_CTRL, WIFI_DATA, WIFI_MGMT, read_pcap
from netlab.report import write_report
from sdfr import wire

T0 = 1_700_000_000.0
R1, R2 = "02:00:00:00:00:00", "02:00:00:00:01:00"
BSSID = "02:5d:f4:00:00:01"
GROUP_MAC = "01:00:5e:7f:ff:fa"


def on_air(pkt: Packet, t: float) -> Packet:
    out = RadioTap(bytes(RadioTap() / pkt))
    out.time = t
    return out


def frames() -> list[Packet]:
    """An IBSS-RSN minute in miniature: r1's beacon, r2's SAE-free open authentication, the
    key handshake, an encrypted SDfR beacon (QoS data, protected), its ACK, and one data frame
    in the clear carrying an SDfR datagram (a fleet without a WiFi key)."""
    beacon = Dot11(type=0, subtype=8, addr1="ff:ff:ff:ff:ff:ff", addr2=R1, addr3=BSSID)
    auth = Dot11(type=0, subtype=11, addr1=R1, addr2=R2, addr3=BSSID)
    eapol = Dot11(type=2, subtype=0, addr1=R2, addr2=R1, addr3=BSSID)
    sealed = Dot11(type=2, subtype=8, FCfield="protected", addr1=GROUP_MAC, addr2=R1, addr3=BSSID)
    ack = Dot11(type=1, subtype=13, addr1=R1)
    clear = Dot11(type=2, subtype=0, addr1=GROUP_MAC, addr2=R2, addr3=BSSID)
    origin = wire.Origin(1, "r2", 7, 0, f"{2:016x}")
    datagram = wire.encode(wire.Alive(origin, "http://10.1.0.2:8701/description.json", 30))
    return [
        on_air(beacon / Dot11Beacon() / Dot11Elt(ID=0, info=b"sdfr-1"), T0),
        on_air(auth / Dot11Auth(algo=0, seqnum=1), T0 + 0.1),
        on_air(eapol / LLC() / SNAP() / EapolLayer(type=3), T0 + 0.2),
        on_air(sealed / Dot11QoS() / Raw(b"\x00" * 120), T0 + 0.3),
        on_air(ack, T0 + 0.31),
        on_air(
            clear / LLC() / SNAP() / IP(src="10.1.0.2", dst="239.255.255.250") / UDP(
                sport=1900, dport=1900
            ) / datagram,
            T0 + 0.4,
        ),
    ]  # fmt: skip


def write_air(folder: Path) -> Path:
    path = folder / "air.pcap"
    wrpcap(str(path), frames())
    info = CaptureInfo(None, "hwsim0", "air", "medium", None, [], "", 2048)
    sidecar_path(path).write_text(json.dumps(info.to_json()))
    return path


def test_802_11_frames_become_records_of_their_own_kinds(tmp_path: Path) -> None:
    recs = list(read_pcap(write_air(tmp_path)))
    kinds = [(r.kind, r.msg_type, r.src_mac, r.direction) for r in recs]
    assert kinds == [
        (WIFI_MGMT, "Beacon", R1, ""),
        (WIFI_MGMT, "Authentication", R2, ""),
        (EAPOL, "Data", R1, ""),
        (WIFI_DATA, "QoS Data", R1, ""),
        (WIFI_CTRL, "Ack", "", ""),
        (SDFR, "Alive", R2, ""),
    ]
    beacon, _, _, sealed, ack, clear = recs
    # The air's bytes: the 802.11 frame, not the capture's radiotap header.
    assert beacon.frame_len == len(frames()[0][Dot11])
    assert sealed.frame_len == 24 + 2 + 120 and sealed.multicast and sealed.dst_mac == GROUP_MAC
    assert ack.frame_len == 10 and not ack.multicast
    # A data frame in the clear is read through to its SDfR datagram, as on Ethernet.
    assert clear.robot == "r2" and clear.src == "10.1.0.2" and clear.payload_len > 0


def test_a_fresh_reader_knows_the_radiotap_link_type(tmp_path: Path) -> None:
    """Read by a process that imported nothing of scapy's 802.11 itself (as `netlab run` and
    `netlab report` are), the air's frames are still 802.11 frames, not raw bytes."""
    path = write_air(tmp_path)
    code = f"from netlab.pcap import read_pcap; print([r.kind for r in read_pcap({str(path)!r})])"
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    assert out.stdout.split("\n")[0] == str(
        [WIFI_MGMT, WIFI_MGMT, EAPOL, WIFI_DATA, WIFI_CTRL, SDFR]
    ), out.stdout + out.stderr
    assert "unknown LL type" not in out.stderr


def test_the_air_is_tallied_by_kind_and_transmitter(tmp_path: Path) -> None:
    recs = list(read_pcap(write_air(tmp_path)))
    air = air_use(recs, {R1: "r1", R2: "r2"})
    assert set(air["by_kind"]) == set(AIR_KINDS)
    assert air["frames"] == 6 and air["bytes"] == sum(r.frame_len for r in recs)
    assert air["by_kind"]["management"]["frames"] == 2
    assert air["by_kind"]["eapol"]["frames"] == 1
    assert air["by_kind"]["control"]["frames"] == 1
    assert air["by_kind"]["data"]["frames"] == 2  # the sealed one and the one in the clear
    per = air["by_transmitter"]
    assert list(per) == ["", "r1", "r2"]  # the ACK has no transmitter address
    assert per["r1"]["frames"] == 3 and per["r2"]["frames"] == 2
    # A transmitter no robot capture names is shown by its MAC.
    assert list(air_use(recs)["by_transmitter"]) == ["", R1, R2]
    # A wired run has no air.
    assert air_use([r for r in recs if r.kind == SDFR]) == {}


def test_a_radio_run_s_report_has_its_air_and_a_wired_run_s_none(tmp_path: Path) -> None:
    radio, wired = tmp_path / "radio", tmp_path / "wired"
    radio.mkdir()
    wired.mkdir()
    write_air(radio)
    report = write_report(radio, records=None, meta={"robots": 2, "medium": "radio"})
    assert report["air"]["frames"] == 6  # type: ignore[index]
    assert report["captures"]["air"]["role"] == "medium"  # type: ignore[index]
    assert "air" not in write_report(wired, records=[], meta={"robots": 2})


def test_a_run_that_captured_the_air_only_names_its_transmitters_from_the_lab_s_radios(
    tmp_path: Path,
) -> None:
    """Without the robots' own captures (capture = "medium"), the run's meta says whose
    radio each address is (`Lab.radio_macs`): the report names robots, not addresses."""
    write_air(tmp_path)
    radios = {"r1": R1, "r2": R2}
    report = write_report(tmp_path, records=None, meta={"robots": 2, "radios": radios})
    assert list(report["air"]["by_transmitter"]) == ["", "r1", "r2"]  # type: ignore[index]
    assert airmedium.perm_address(hwsim.hwsim_address(R2)) == R2  # what radio_macs undoes


def test_the_air_read_from_802_11_headers_is_what_scapy_dissects(tmp_path: Path) -> None:
    """The air's records come from the 802.11 header read directly (scapy dissected every
    frame in 5 ms, minutes per run in the emulated VM): for every kind of frame, the same
    records scapy's dissection gives."""
    from scapy.layers.dot11 import Dot11Action, Dot11ProbeReq
    from scapy.utils import PcapReader

    from netlab import pcap

    extra = [
        Dot11(type=2, subtype=4, addr1=R1, addr2=R2, addr3=BSSID),  # null data
        Dot11(type=2, subtype=12, addr1=R1, addr2=R2, addr3=BSSID) / Dot11QoS(),  # QoS null
        Dot11(type=2, subtype=0, FCfield=3, addr1=R1, addr2=R2, addr3=BSSID,
              addr4=R1) / LLC() / SNAP() / EapolLayer(type=3),  # four addresses
        Dot11(type=2, subtype=8, addr1=R2, addr2=R1, addr3=BSSID) / Dot11QoS() / LLC()
        / SNAP() / EapolLayer(type=3),  # QoS data carrying EAPOL
        Dot11(type=2, subtype=8, addr1=R2, addr2=R1, addr3=BSSID) / Dot11QoS() / LLC()
        / SNAP(code=0x88B5) / Raw(b"x" * 8),  # another ethertype, in the clear
        Dot11(type=1, subtype=11, addr1=R1, addr2=R2),  # RTS: a control frame with addr2
        Dot11(type=1, subtype=12, addr1=R2),  # CTS
        Dot11(type=0, subtype=4, addr1="ff:ff:ff:ff:ff:ff", addr2=R2, addr3=BSSID)
        / Dot11ProbeReq() / Dot11Elt(ID=0, info=b"sdfr-fleet-1"),
        Dot11(type=0, subtype=13, addr1=R1, addr2=R2, addr3=BSSID) / Dot11Action(category=13),
    ]  # fmt: skip
    path = tmp_path / "air.pcap"
    all_frames = frames() + [on_air(f, T0 + 1 + i / 10) for i, f in enumerate(extra)]
    wrpcap(str(path), all_frames)
    ours = list(read_pcap(path, role="medium"))
    with PcapReader(str(path)) as reader:
        theirs = [pcap._record(p, "air", None) for p in reader]
    assert len(ours) == len(all_frames)
    assert ours == theirs
    assert [r.kind for r in ours[len(frames()) :]] == [
        WIFI_DATA, WIFI_DATA, EAPOL, EAPOL, WIFI_DATA, WIFI_CTRL, WIFI_CTRL, WIFI_MGMT, WIFI_MGMT
    ]  # fmt: skip
