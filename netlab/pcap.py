"""Captured frames as records: `read_pcap` streams a pcap into one `Record` per SDfR datagram,
ARP frame or other frame.  A classic pcap of Ethernet or radiotap frames is read from the
frames' headers, its SDfR datagrams through `netlab.datagram.describe` (the daemon's own
parser); scapy (with the `netlab.sdfr_layer.SDfR` layer) dissects only the frames those
readers leave to it, and pcapng files.  Both ways give the same records (test_analysis.py,
test_air_capture.py).

Direction.  A robot's capture (its ``eth0``) holds what it sent and what reached it: a frame
is ``tx`` when its source MAC is the interface's own (from the ``.json`` that
`netlab.capture.Capture` writes next to the pcap), else ``rx``.  A medium capture (the bridge)
sees every frame put on the air once, with no direction.

Sizes.  ``payload_len`` is the UDP payload (the SDfR datagram, as the daemon sees it);
``frame_len`` the whole Ethernet frame as captured (Ethernet + IP + UDP headers + payload, no
preamble or FCS).

The air.  A radio lab's medium capture (``hwsim0``: every 802.11 frame any radio sent, with
a radiotap header) has frames an Ethernet capture never sees: management (beacons, probes,
SAE authentication, mesh peering), control (ACKs) and data frames encrypted with the fleet's
key, whose payload cannot be read (kinds "wifi-mgmt", "wifi-ctrl", "wifi-data"), and EAPOL
(the WPA2 handshake, kind "eapol"); ``msg_type`` is the frame's subtype ("Beacon", "Ack").
A data frame that is not encrypted is read through to its IP datagram like an Ethernet one.
For these ``src_mac`` is the transmitter (802.11's address 2; none for an ACK), ``dst_mac``
the receiver (address 1), and ``frame_len`` the 802.11 frame (header and body, without the
radiotap header, which is not on the air, and without the PHY's preamble).

Times are the capture's timestamps: UNIX seconds (``time.time()`` clock).
"""

from __future__ import annotations

import ipaddress
import json
import struct
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

from netlab.capture import CaptureInfo
from netlab.datagram import PORT, view
from netlab.errors import NetlabError
from netlab.naming import mac_text

__all__ = [
    "ARP",
    "EAPOL",
    "OTHER",
    "RX",
    "SDFR",
    "TX",
    "WIFI_CTRL",
    "WIFI_DATA",
    "WIFI_KINDS",
    "WIFI_MGMT",
    "PcapError",
    "Record",
    "capture_infos",
    "read_pcap",
    "read_run",
]

SDFR = "sdfr"
ARP = "arp"
OTHER = "other"
WIFI_MGMT = "wifi-mgmt"
WIFI_CTRL = "wifi-ctrl"
WIFI_DATA = "wifi-data"  # encrypted (or without a payload): not readable here
EAPOL = "eapol"
#: The kinds only an 802.11 capture has.
WIFI_KINDS = (WIFI_MGMT, WIFI_CTRL, WIFI_DATA, EAPOL)
TX = "tx"
RX = "rx"


class PcapError(NetlabError, ValueError):
    """A file that is not a readable pcap."""


@dataclass(frozen=True, slots=True)
class Record:
    """One captured frame: an SDfR datagram (kind "sdfr"), an ARP frame ("arp") or other."""

    time: float
    capture: str  # label of the capture it comes from
    direction: str  # "tx", "rx", or "" (medium capture, or direction unknown)
    kind: str  # "sdfr", "arp", "other", or one of WIFI_KINDS
    src_mac: str
    dst_mac: str
    src: str  # IP source; for ARP the sender protocol address
    dst: str  # IP destination; for ARP the target protocol address
    multicast: bool  # IP destination is a multicast group
    frame_len: int  # the whole frame on the wire (pcap original length)
    payload_len: int = 0  # UDP payload (0 for ARP)
    sport: int | None = None
    dport: int | None = None
    msg_type: str = ""  # sdfr_layer.MSG_TYPES for "sdfr"; "ARP" for "arp"; 802.11's subtype
    robot: str | None = None  # the sender's robot id (SDfR header)
    fleet: int | None = None
    boot: int | None = None
    version: int | None = None
    part: int | None = None  # 0-based
    parts: int | None = None
    services: int | None = None
    seq: int | None = None  # Discovery/Response: a unicast ping and its reply
    ping: int | None = None  # Response: the sender's own ping riding on its reply
    reason: str | None = None  # Reject: why
    arp_op: int | None = None  # 1 request, 2 reply

    @property
    def type_key(self) -> str:
        """The message type, pings apart: "Ping" (Discovery with seq), "Ping reply"."""
        if self.seq is not None:
            if self.msg_type == "Discovery":
                return "Ping"
            if self.msg_type == "Response":
                return "Ping reply"
        return self.msg_type

    def to_json(self) -> dict[str, object]:
        return asdict(self)


# ---------------------------------------------------------------------------------------------
# Reading pcaps


def read_pcap(
    path: Path,
    *,
    label: str | None = None,
    own_mac: str | None = None,
    role: str | None = None,
) -> Iterator[Record]:
    """Records of the SDfR datagrams, ARP and other frames in one pcap, in file order.

    `label`, `own_mac` and `role` ("robot" or "medium") default to what ``PATH.json`` (written
    by `netlab.capture.Capture`) says, else the file name without extension, no MAC, "robot".
    Without a MAC, or for the medium, records have no direction.
    """
    path = Path(path)
    meta = _sidecar(path)
    label = label or str(meta.get("label") or path.stem)
    own_mac = (own_mac or meta.get("mac") or "").lower() or None
    role = role or str(meta.get("role") or "robot")
    try:
        if path.stat().st_size == 0:  # killed before tcpdump flushed the file header
            return
    except OSError as exc:
        raise PcapError(f"cannot read {path}: {exc}") from None
    mac = own_mac if role != "medium" else None
    link = _link_type(path)
    if link in (DLT_EN10MB, DLT_RADIOTAP):
        yield from _read_headers(path, link, label, mac)
    else:  # pcapng, or another link type: scapy's reader and dissection
        yield from _read_scapy(path, label, mac)


def _read_scapy(path: Path, label: str, own_mac: str | None) -> Iterator[Record]:
    """Every frame dissected by scapy (`_record`): for what `_read_headers` does not read
    (pcapng, other link types)."""
    import scapy.layers.dot11  # noqa: F401  (radiotap, 802.11)
    from scapy.error import Scapy_Exception
    from scapy.utils import PcapReader

    import netlab.sdfr_layer  # noqa: F401  (binds the SDfR layer to UDP port 1900)

    try:
        reader = PcapReader(str(path))
    except (Scapy_Exception, OSError) as exc:
        raise PcapError(f"{path} is not a pcap file: {exc}") from None
    with reader:
        for pkt in reader:
            rec = _record(pkt, label, own_mac)
            if rec is not None:
                yield rec


def _frames(path: Path) -> Iterator[tuple[bytes, float, int]]:
    """A classic pcap's frames: (bytes as captured, time, length on the wire)."""
    try:
        f = path.open("rb")
    except OSError as exc:
        raise PcapError(f"cannot read {path}: {exc}") from None
    with f:
        head = f.read(24)
        order, scale = _MAGIC[head[:4]]
        rec = struct.Struct(order + "IIII")
        while True:
            raw = f.read(16)
            if len(raw) < 16:  # the end, or a record cut short by a kill
                return
            sec, frac, caplen, wirelen = rec.unpack(raw)
            data = f.read(caplen)
            if len(data) < caplen:
                return
            yield data, sec + frac / scale, wirelen


def merge(sources: Iterable[tuple[Path, float]], out: Path) -> int:
    """Write one classic pcap (microseconds) of the frames of every classic pcap in `sources`,
    each with its clock's offset taken off its times (a host's clock minus the controller's),
    in time order; how many frames.  The sources share one link type (PcapError if not)."""
    frames: list[tuple[float, bytes, int]] = []
    link: int | None = None
    for path, offset in sources:
        try:
            head = path.read_bytes()[:24]
        except OSError as exc:
            raise PcapError(f"cannot read {path}: {exc}") from None
        if len(head) < 24 or head[:4] not in _MAGIC:
            raise PcapError(f"{path}: not a classic pcap")
        kind = struct.unpack(_MAGIC[head[:4]][0] + "I", head[20:24])[0]
        if link is not None and kind != link:
            raise PcapError(f"{path}: link type {kind}, the others' {link}: cannot merge")
        link = kind
        frames.extend((t - offset, data, wirelen) for data, t, wirelen in _frames(path))
    frames.sort(key=lambda f: f[0])
    rec = struct.Struct("<IIII")
    tmp = out.with_name(out.name + ".tmp")
    with tmp.open("wb") as f:
        f.write(struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, SNAP_MAX, link or 1))
        for t, data, wirelen in frames:
            sec = int(t)
            f.write(rec.pack(sec, min(round((t - sec) * 1e6), 999_999), len(data), wirelen))
            f.write(data)
    tmp.replace(out)
    return len(frames)


#: The snapshot length a merged pcap's header states (any frame captured here fits).
SNAP_MAX = 262_144


#: IP protocols read as "other" without scapy (TCP, IGMP); UDP is read on.
_OTHER_PROTOCOLS = (6, 2)


def _ether_record(
    data: bytes, t: float, wirelen: int, label: str, own_mac: str | None
) -> Record | None:
    """The record of one Ethernet frame from its headers, as `_record` makes it through
    scapy; None when only scapy can tell (anything but ARP over IPv4 and unfragmented IPv4
    carrying UDP, TCP or IGMP, or a frame cut short)."""
    if len(data) < 14:
        return None
    src_mac, dst_mac = mac_text(data[6:12]), mac_text(data[0:6])
    ethertype = int.from_bytes(data[12:14], "big")
    make = _maker(t, label, src_mac, dst_mac, wirelen, own_mac)
    if ethertype == 0x0806:
        if len(data) < 42 or data[14:20] != b"\x00\x01\x08\x00\x06\x04":
            return None
        return make(
            kind=ARP,
            src=_ipv4(data[28:32]),
            dst=_ipv4(data[38:42]),
            multicast=False,
            msg_type="ARP",
            arp_op=int.from_bytes(data[20:22], "big"),
        )
    if ethertype != 0x0800 or len(data) < 34 or data[14] >> 4 != 4:
        return None
    ihl = (data[14] & 0xF) * 4
    total = int.from_bytes(data[16:18], "big")
    frag = int.from_bytes(data[20:22], "big")
    proto = data[23]
    if ihl < 20 or frag & 0x3FFF or total < ihl or len(data) < 14 + total:
        return None  # options cut short, a fragment, or the frame cut short: scapy's
    src, dst = _ipv4(data[26:30]), _ipv4(data[30:34])
    if proto in _OTHER_PROTOCOLS:
        return make(kind=OTHER, src=src, dst=dst, multicast=_multicast(dst))
    if proto != 17 or total < ihl + 8:
        return None
    udp = data[14 + ihl : 14 + total]
    sport, dport, ulen = struct.unpack_from("!HHH", udp)
    if PORT not in (sport, dport):
        return make(kind=OTHER, src=src, dst=dst, multicast=_multicast(dst))
    if ulen < 8:
        return None
    return make(
        kind=SDFR,
        src=src,
        dst=dst,
        multicast=_multicast(dst),
        payload_len=ulen - 8,
        sport=sport,
        dport=dport,
        **_datagram(view(udp[8:ulen])),
    )


@lru_cache(maxsize=4096)
def _ipv4(raw: bytes) -> str:
    return ".".join(str(b) for b in raw)


#: pcap's link types: Ethernet (a robot's or the wired medium's), radiotap + 802.11 (hwsim0's).
DLT_EN10MB = 1
DLT_RADIOTAP = 127
#: A classic pcap's magic: byte order and the timestamps' fraction (micro- or nanoseconds).
_MAGIC = {
    b"\xd4\xc3\xb2\xa1": ("<", 1e6),
    b"\x4d\x3c\xb2\xa1": ("<", 1e9),
    b"\xa1\xb2\xc3\xd4": (">", 1e6),
    b"\xa1\xb2\x3c\x4d": (">", 1e9),
}
_SNAP = b"\xaa\xaa\x03\x00\x00\x00"
#: Ethertypes read on through scapy (like an Ethernet frame's), and EAPOL's.
_READ_ON = (0x0800, 0x86DD, 0x0806)
_ETH_EAPOL = 0x888E


def _link_type(path: Path) -> int | None:
    """The link type of a classic pcap's header (None for pcapng or anything else)."""
    try:
        with path.open("rb") as f:
            head = f.read(24)
    except OSError as exc:
        raise PcapError(f"cannot read {path}: {exc}") from None
    if len(head) < 24 or head[:4] not in _MAGIC:
        return None
    return int(struct.unpack_from(_MAGIC[head[:4]][0] + "I", head, 20)[0])


def _read_headers(path: Path, link: int, label: str, own_mac: str | None) -> Iterator[Record]:
    """A classic pcap's records, each frame read from its headers (`_ether_record`,
    `_air_record`); scapy dissects only what those leave to it (IPv6, fragments, ICMP, VLANs;
    an 802.11 data frame in the clear carrying IP or ARP).  (scapy took about a millisecond an
    Ethernet frame here, 5 ms an 802.11 frame, and fifty times that in the VM tiers' emulated
    VM, minutes per run.)"""
    direct = _air_record if link == DLT_RADIOTAP else _ether_record
    for data, t, wirelen in _frames(path):
        rec = direct(data, t, wirelen, label, own_mac)
        if rec is None:
            rec = _record(_dissect(data, link, t, wirelen), label, own_mac)
        if rec is not None:
            yield rec


def _dissect(data: bytes, link: int, t: float, wirelen: int) -> Any:
    """scapy's dissection of one frame of a capture of link type `link`."""
    from scapy.layers.dot11 import RadioTap
    from scapy.layers.l2 import Ether

    import netlab.sdfr_layer  # noqa: F401  (binds the SDfR layer to UDP port 1900)

    pkt = RadioTap(data) if link == DLT_RADIOTAP else Ether(data)
    pkt.time, pkt.wirelen = t, wirelen
    return pkt


def _air_record(
    data: bytes, t: float, wirelen: int, label: str, own_mac: str | None
) -> Record | None:
    """The record of one radiotap frame from its 802.11 header, as `_record` makes it
    through scapy; None when only scapy can tell (a data frame in the clear carrying IP or
    ARP, anything short or odd)."""
    from scapy.layers.dot11 import _dot11_subtypes

    if len(data) < 4:
        return None
    rt_len = int.from_bytes(data[2:4], "little")
    frame = data[rt_len:]
    if len(frame) < 10:
        return None
    fc, flags = frame[0], frame[1]
    ftype, subtype = (fc >> 2) & 3, (fc >> 4) & 0xF
    has_addr2 = ftype not in (1, 3) or subtype in (4, 5, 6, 8, 9, 10, 11, 14, 15)
    if has_addr2 and len(frame) < 16:
        return None
    if ftype == 0:
        kind = WIFI_MGMT
    elif ftype != 2:
        kind = WIFI_CTRL
    elif flags & 0x40 or subtype & 0x4:  # protected, or no payload (null, CF-)
        kind = WIFI_DATA
    else:
        header = 24 + (6 if flags & 0x3 == 0x3 else 0)
        if subtype & 0x8:  # QoS control, and HT control when the order bit says so
            header += 2 + (4 if flags & 0x80 else 0)
        body = frame[header:]
        if body[:6] != _SNAP or len(body) < 8:
            return None
        ethertype = int.from_bytes(body[6:8], "big")
        if ethertype in _READ_ON:
            return None
        kind = EAPOL if ethertype == _ETH_EAPOL else WIFI_DATA
    src_mac = mac_text(frame[10:16]) if has_addr2 else ""
    return Record(
        time=t,
        capture=label,
        direction=_direction(src_mac, own_mac),
        kind=kind,
        src_mac=src_mac,
        dst_mac=mac_text(frame[4:10]),
        src="",
        dst="",
        multicast=bool(frame[4] & 1),
        frame_len=wirelen - rt_len,
        msg_type=str(_dot11_subtypes.get(ftype, {}).get(subtype, subtype)),
    )


def read_run(
    sources: Path | Iterable[Path],
) -> list[Record]:
    """Records of every ``*.pcap`` in a directory (or of the given pcaps), by time."""
    if isinstance(sources, Path):
        paths = sorted(sources.glob("*.pcap")) if sources.is_dir() else [sources]
    else:
        paths = [Path(p) for p in sources]
    out: list[Record] = []
    for path in paths:
        out.extend(read_pcap(path))
    out.sort(key=lambda r: r.time)
    return out


def capture_infos(run_dir: Path) -> dict[str, CaptureInfo]:
    """What the ``*.pcap.json`` files in `run_dir` say about its captures, by label."""
    out: dict[str, CaptureInfo] = {}
    for pcap in sorted(Path(run_dir).glob("*.pcap")):
        meta = _sidecar(pcap)
        if meta:
            info = CaptureInfo.from_json(meta)
            out[info.label or pcap.stem] = info
    return out


def _sidecar(path: Path) -> dict[str, Any]:
    side = path.with_name(path.name + ".json")
    try:
        obj = json.loads(side.read_text())
    except (OSError, ValueError):
        return {}
    return obj if isinstance(obj, dict) else {}


def _record(pkt: Any, label: str, own_mac: str | None) -> Record | None:
    from scapy.layers.inet import IP, UDP
    from scapy.layers.inet6 import IPv6
    from scapy.layers.l2 import ARP as ArpLayer

    from netlab.sdfr_layer import SDfR, describe

    t = float(pkt.time)
    frame_len = int(pkt.wirelen or len(pkt))
    air = _dot11(pkt)
    if air is not None:
        frame_len -= int(pkt.len or 0)  # the radiotap header: the capture's, not the air's
        src_mac, dst_mac = str(air.addr2 or "").lower(), str(air.addr1 or "").lower()
    else:
        src_mac = str(getattr(pkt, "src", "") or "").lower() if _is_ether(pkt) else ""
        dst_mac = str(getattr(pkt, "dst", "") or "").lower() if _is_ether(pkt) else ""
    make = _maker(t, label, src_mac, dst_mac, frame_len, own_mac)
    wifi = _wifi_kind(pkt, air) if air is not None else None
    if wifi is not None:
        group = bool(dst_mac) and int(dst_mac[:2], 16) & 1 == 1
        subtype = str(air.sprintf("%Dot11.subtype%"))
        return make(kind=wifi, src="", dst="", multicast=group, msg_type=subtype)
    if ArpLayer in pkt:
        arp = pkt[ArpLayer]
        return make(
            kind=ARP,
            src=str(arp.psrc),
            dst=str(arp.pdst),
            multicast=False,
            msg_type="ARP",
            arp_op=int(arp.op),
        )
    ip = pkt.getlayer(IP) or pkt.getlayer(IPv6)
    if ip is None:
        return make(kind=OTHER, src="", dst="", multicast=False)
    src, dst = str(ip.src), str(ip.dst)
    udp = pkt.getlayer(UDP)
    if udp is None or PORT not in (udp.sport, udp.dport):
        return make(kind=OTHER, src=src, dst=dst, multicast=_multicast(dst))
    layer = udp.getlayer(SDfR)
    if layer is not None:
        data: bytes = layer.load
        fields: Mapping[str, Any] = layer.fields
    else:  # e.g. an empty payload, or a first fragment
        data = bytes(udp.payload)
        fields = describe(data)
    size = int(udp.len) - 8 if udp.len is not None and int(udp.len) >= 8 else len(data)
    return make(
        kind=SDFR,
        src=src,
        dst=dst,
        multicast=_multicast(dst),
        payload_len=size,
        sport=int(udp.sport),
        dport=int(udp.dport),
        **_datagram(fields),
    )


def _maker(
    t: float, label: str, src_mac: str, dst_mac: str, frame_len: int, own_mac: str | None
) -> Callable[..., Record]:
    """Records of one frame: its time, capture, direction, MACs and length set."""
    direction = _direction(src_mac, own_mac)

    def make(**kw: Any) -> Record:
        return Record(
            time=t,
            capture=label,
            direction=direction,
            src_mac=src_mac,
            dst_mac=dst_mac,
            frame_len=frame_len,
            **kw,
        )

    return make


#: The fields of an SDfR datagram's view that a record carries as they are.
_DATAGRAM_FIELDS = ("robot", "fleet", "boot", "version", "part", "parts", "services", "seq",
                    "ping", "reason")  # fmt: skip


def _datagram(fields: Mapping[str, Any]) -> dict[str, Any]:
    """A record's SDfR fields from a datagram's view (`netlab.datagram.view`)."""
    return {
        "msg_type": str(fields.get("msg_type") or "Reject"),
        **{k: fields.get(k) for k in _DATAGRAM_FIELDS},
    }


def _direction(src_mac: str, own_mac: str | None) -> str:
    """TX when the capture's own interface sent the frame, RX when another did; "" when the
    capture has no own interface (the medium's) or the frame no sender (an ACK)."""
    return "" if own_mac is None or not src_mac else TX if src_mac == own_mac else RX


def _dot11(pkt: Any) -> Any:
    """The 802.11 frame of a radiotap record, else None."""
    from scapy.layers.dot11 import Dot11, RadioTap

    return pkt.getlayer(Dot11) if isinstance(pkt, RadioTap) else None


def _wifi_kind(pkt: Any, air: Any) -> str | None:
    """The kind of an 802.11 frame; None for a data frame in the clear that carries IP or
    ARP (read on like an Ethernet frame)."""
    from scapy.layers.eap import EAPOL as EapolLayer
    from scapy.layers.inet import IP
    from scapy.layers.inet6 import IPv6
    from scapy.layers.l2 import ARP as ArpLayer

    if air.type == 0:
        return WIFI_MGMT
    if air.type != 2:  # control (and the rare extension frames)
        return WIFI_CTRL
    if EapolLayer in pkt:
        return EAPOL
    if air.FCfield.protected or not (IP in pkt or IPv6 in pkt or ArpLayer in pkt):
        return WIFI_DATA
    return None


def _is_ether(pkt: Any) -> bool:
    from scapy.layers.l2 import Ether

    return isinstance(pkt, Ether)


@lru_cache(maxsize=1024)
def _multicast(addr: str) -> bool:
    try:
        return ipaddress.ip_address(addr).is_multicast
    except ValueError:
        return False
