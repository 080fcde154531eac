"""Captured traffic as records, and the figures made from them.

`read_pcap` streams a pcap (scapy's `PcapReader`, with the `netlab.sdfr_layer.SDfR` layer) into
one `Record` per SDfR datagram or ARP frame; everything else here is a pure function over
records, so it is tested with synthetic pcaps and no root.

Who sent, who received.  A robot's capture (its ``eth0``) holds what it sent and what reached
it: a frame is ``tx`` when its source MAC is the interface's own (from the ``.json`` that
`netlab.capture.Capture` writes next to the pcap), else ``rx``.  A medium capture (the bridge)
sees every frame put on the air once, with no direction.  So:

* sent datagrams (`transmissions`) are the ``tx`` records when there are any, else the records
  without a direction (a medium capture, or pcaps without metadata): each datagram once;
* a robot's received datagrams are the ``rx`` records of its own capture: what reached its
  interface (after the medium's loss), whether or not the daemon accepted it.

Senders are named by the robot id in the datagram; receivers by their capture's owner, the
robot whose datagrams that capture sent (falling back to the capture's label).

Sizes.  ``payload_bytes`` is the UDP payload (the SDfR datagram, as the daemon sees it);
``frame_bytes`` the whole Ethernet frame as captured (Ethernet + IP + UDP headers + payload, no
preamble or FCS).  Reports give both; 1 kB = 1000 bytes.  ARP is counted apart (`arp_counts`).

Times are the capture's timestamps: UNIX seconds (``time.time()`` clock).
"""

from __future__ import annotations

import ipaddress
import json
import math
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, TypeVar

from netlab.capture import CaptureInfo
from netlab.errors import NetlabError

__all__ = [
    "PAPER_BEACON_S",
    "PAPER_CONDITIONS",
    "PAPER_ROBOTS",
    "PAPER_RX_KB_5MIN",
    "PAPER_SERVICES_PER_ROBOT",
    "PAPER_TX_KB_5MIN",
    "ArpCounts",
    "PcapError",
    "PingTally",
    "Record",
    "RobotTraffic",
    "Series",
    "Totals",
    "arp_counts",
    "arp_counts_by_sender",
    "capture_infos",
    "capture_owners",
    "count_updates",
    "natural_order",
    "neighbour_agreement",
    "paper_measure",
    "per_second",
    "per_type",
    "ping_delivery",
    "read_pcap",
    "read_run",
    "received_per_robot",
    "receptions",
    "rejects",
    "sent_per_robot",
    "traffic_per_robot",
    "transmissions",
]

#: The paper's figure 6: kilobytes per robot over a 5-minute run (2 to 6 robots, static and
#: moving fleets).
PAPER_TX_KB_5MIN = (220, 320)
PAPER_RX_KB_5MIN = (540, 850)
FIVE_MINUTES_S = 300.0
#: The conditions of those figures: the default 10 s beacon, 2 to 6 robots, each with 100
#: simulated services of which 30, 50 or 70 % were published, runs of 5 minutes.
PAPER_BEACON_S = 10.0
PAPER_ROBOTS = (2, 6)
PAPER_SERVICES_PER_ROBOT = (30, 70)
PAPER_CONDITIONS = "10 s beacon, 2-6 robots, 30-70 services each, 5 min runs"

_T = TypeVar("_T")

SDFR = "sdfr"
ARP = "arp"
OTHER = "other"
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
    kind: str  # "sdfr", "arp" or "other"
    src_mac: str
    dst_mac: str
    src: str  # IP source; for ARP the sender protocol address
    dst: str  # IP destination; for ARP the target protocol address
    multicast: bool  # IP destination is a multicast group
    frame_len: int  # the whole frame on the wire (pcap original length)
    payload_len: int = 0  # UDP payload (0 for ARP)
    sport: int | None = None
    dport: int | None = None
    msg_type: str = ""  # sdfr_layer.MSG_TYPES for "sdfr"; "ARP" for "arp"
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


@dataclass(slots=True)
class Totals:
    """Datagrams and their bytes, summed."""

    datagrams: int = 0
    payload_bytes: int = 0
    frame_bytes: int = 0

    def add(self, rec: Record) -> None:
        self.datagrams += 1
        self.payload_bytes += rec.payload_len
        self.frame_bytes += rec.frame_len

    def to_json(self) -> dict[str, int]:
        return {
            "datagrams": self.datagrams,
            "payload_bytes": self.payload_bytes,
            "frame_bytes": self.frame_bytes,
        }


@dataclass(slots=True)
class RobotTraffic:
    tx: Totals = field(default_factory=Totals)
    rx: Totals = field(default_factory=Totals)


@dataclass(frozen=True, slots=True)
class Series:
    """Values per time bin: bin i covers [start + i*step, start + (i+1)*step)."""

    start: float
    step: float
    values: dict[str, list[float]]  # key -> one value per bin

    @property
    def bins(self) -> int:
        return max((len(v) for v in self.values.values()), default=0)

    @property
    def times(self) -> list[float]:
        """Start of each bin, in seconds since `start`."""
        return [i * self.step for i in range(self.bins)]


@dataclass(slots=True)
class ArpCounts:
    """ARP frames by purpose (RFC 5227 terms)."""

    probes: int = 0  # request with sender IP 0.0.0.0
    announcements: int = 0  # sender IP == target IP (gratuitous), request or reply
    requests: int = 0  # other requests
    replies: int = 0  # other replies

    def to_json(self) -> dict[str, int]:
        return {
            "probes": self.probes,
            "announcements": self.announcements,
            "requests": self.requests,
            "replies": self.replies,
        }


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
    from scapy.error import Scapy_Exception
    from scapy.utils import PcapReader

    import netlab.sdfr_layer  # noqa: F401  (binds the SDfR layer to UDP port 1900)

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
    try:
        reader = PcapReader(str(path))
    except (Scapy_Exception, OSError) as exc:
        raise PcapError(f"{path} is not a pcap file: {exc}") from None
    with reader:
        for pkt in reader:
            rec = _record(pkt, label, own_mac if role != "medium" else None)
            if rec is not None:
                yield rec


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
    src_mac = str(getattr(pkt, "src", "") or "").lower() if _is_ether(pkt) else ""
    dst_mac = str(getattr(pkt, "dst", "") or "").lower() if _is_ether(pkt) else ""
    direction = "" if own_mac is None or not src_mac else TX if src_mac == own_mac else RX

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
    if udp is None or 1900 not in (udp.sport, udp.dport):
        return make(kind=OTHER, src=src, dst=dst, multicast=_multicast(dst))
    layer = udp.getlayer(SDfR)
    if layer is not None:
        data: bytes = layer.load
        view: Mapping[str, Any] = layer.fields
    else:  # e.g. an empty payload, or a first fragment
        data = bytes(udp.payload)
        view = describe(data)
    size = int(udp.len) - 8 if udp.len is not None and int(udp.len) >= 8 else len(data)
    return make(
        kind=SDFR,
        src=src,
        dst=dst,
        multicast=_multicast(dst),
        payload_len=size,
        sport=int(udp.sport),
        dport=int(udp.dport),
        msg_type=str(view.get("msg_type") or "Reject"),
        robot=view.get("robot"),
        fleet=view.get("fleet"),
        boot=view.get("boot"),
        version=view.get("version"),
        part=view.get("part"),
        parts=view.get("parts"),
        services=view.get("services"),
        seq=view.get("seq"),
        ping=view.get("ping"),
        reason=view.get("reason"),
    )


def _is_ether(pkt: Any) -> bool:
    from scapy.layers.l2 import Ether

    return isinstance(pkt, Ether)


@lru_cache(maxsize=1024)
def _multicast(addr: str) -> bool:
    try:
        return ipaddress.ip_address(addr).is_multicast
    except ValueError:
        return False


# ---------------------------------------------------------------------------------------------
# Selections


def transmissions(records: Iterable[Record], *, kind: str = SDFR) -> list[Record]:
    """Each frame of `kind` put on the air, once: the "tx" records if there are any, else the
    records without a direction (medium capture, or pcaps without metadata)."""
    recs = [r for r in records if r.kind == kind]
    tx = [r for r in recs if r.direction == TX]
    return tx if tx else [r for r in recs if not r.direction]


def receptions(records: Iterable[Record]) -> list[Record]:
    """SDfR datagrams that reached a robot's interface ("rx" records)."""
    return [r for r in records if r.kind == SDFR and r.direction == RX]


def capture_owners(records: Iterable[Record]) -> dict[str, str]:
    """Capture label -> the robot id it belongs to: the sender of most of its "tx" datagrams."""
    seen: dict[str, Counter[str]] = defaultdict(Counter)
    for r in records:
        if r.kind == SDFR and r.direction == TX and r.robot is not None:
            seen[r.capture][r.robot] += 1
    return {label: c.most_common(1)[0][0] for label, c in seen.items()}


def _address_owners(records: Iterable[Record]) -> dict[str, str]:
    """Source IP -> the robot id most datagrams from it carry."""
    seen: dict[str, Counter[str]] = defaultdict(Counter)
    for r in records:
        if r.kind == SDFR and r.robot is not None:
            seen[r.src][r.robot] += 1
    return {addr: c.most_common(1)[0][0] for addr, c in seen.items()}


class _Senders:
    """Names the robot that sent a record, also one without a robot id (junk, plain SSDP)."""

    def __init__(self, records: Sequence[Record]) -> None:
        self.captures = capture_owners(records)
        self.addresses = _address_owners(records)

    def __call__(self, rec: Record) -> str:
        if rec.robot is not None:
            return rec.robot
        if rec.direction == TX and rec.capture in self.captures:
            return self.captures[rec.capture]
        return self.addresses.get(rec.src) or rec.src or rec.src_mac or "?"


# ---------------------------------------------------------------------------------------------
# Figures


def sent_per_robot(records: Iterable[Record]) -> dict[str, Totals]:
    """Datagrams and bytes each robot sent (its `transmissions`), by robot id."""
    recs = list(records)
    sender = _Senders(recs)
    out: dict[str, Totals] = defaultdict(Totals)
    for r in transmissions(recs):
        out[sender(r)].add(r)
    return _sorted(out)


def received_per_robot(records: Iterable[Record]) -> dict[str, Totals]:
    """Datagrams and bytes that reached each robot's interface, by the capture's owner."""
    recs = list(records)
    owners = capture_owners(recs)
    out: dict[str, Totals] = defaultdict(Totals)
    for r in receptions(recs):
        out[owners.get(r.capture, r.capture)].add(r)
    return _sorted(out)


def traffic_per_robot(records: Iterable[Record]) -> dict[str, RobotTraffic]:
    """TX (`sent_per_robot`) and RX (`received_per_robot`) per robot."""
    recs = list(records)
    out: dict[str, RobotTraffic] = defaultdict(RobotTraffic)
    for robot, totals in sent_per_robot(recs).items():
        out[robot].tx = totals
    for robot, totals in received_per_robot(recs).items():
        out[robot].rx = totals
    return _sorted(out)


def per_type(records: Iterable[Record], *, split_pings: bool = True) -> dict[str, Totals]:
    """Sent datagrams and bytes per message type (`Record.type_key`, or `msg_type`)."""
    out: dict[str, Totals] = defaultdict(Totals)
    for r in transmissions(records):
        out[r.type_key if split_pings else r.msg_type].add(r)
    return dict(sorted(out.items()))


def rejects(records: Iterable[Record]) -> dict[str, int]:
    """Sent datagrams that `sdfr.wire.decode` rejects, per reason."""
    c = Counter(r.reason or "?" for r in transmissions(records) if r.msg_type == "Reject")
    return dict(sorted(c.items()))


def per_second(
    records: Iterable[Record],
    *,
    by: str = "type",
    value: str = "datagrams",
    step: float = 1.0,
    start: float | None = None,
    end: float | None = None,
) -> Series:
    """A time series: `value` ("datagrams", "payload_bytes", "frame_bytes") per `step` seconds,
    one series per message type (`by="type"`), per sender (`"robot"`, over `transmissions`),
    per receiver (`"receiver"`, over `receptions`) or in all (`"total"`).

    Bins start at `start` (default: the first record) and cover up to `end` (default: the
    last record; the last bin includes `end`).  Values are sums per bin; divide by `step` for a
    rate.
    """
    if step <= 0:
        raise ValueError(f"step must be positive, not {step}")
    if value not in ("datagrams", "payload_bytes", "frame_bytes"):
        raise ValueError(f"value must be datagrams, payload_bytes or frame_bytes: {value!r}")
    recs = list(records)
    owners = capture_owners(recs)
    key: Callable[[Record], str]
    if by == "type":
        chosen, key = transmissions(recs), lambda r: r.type_key
    elif by == "robot":
        chosen, key = transmissions(recs), _Senders(recs)
    elif by == "receiver":
        chosen, key = receptions(recs), lambda r: owners.get(r.capture, r.capture)
    elif by == "total":
        chosen, key = transmissions(recs), lambda r: "total"
    else:
        raise ValueError(f"by must be type, robot, receiver or total: {by!r}")
    if start is None:
        start = min((r.time for r in chosen), default=0.0)
    if end is None:
        end = max((r.time for r in chosen), default=start)
    bins = max(1, math.ceil((end - start) / step))
    values: dict[str, list[float]] = {}
    for r in chosen:
        if not start <= r.time <= end:
            continue
        i = min(math.floor((r.time - start) / step), bins - 1)  # `end` itself: the last bin
        row = values.setdefault(key(r), [0.0] * bins)
        row[i] += (
            1
            if value == "datagrams"
            else r.payload_len
            if value == "payload_bytes"
            else r.frame_len
        )
    return Series(start, step, dict(sorted(values.items())))


def paper_measure(records: Iterable[Record], *, duration: float | None = None) -> dict[str, Any]:
    """The paper's measure: TX and RX kilobytes per robot over the run, in JSON form.

    Both sizes are given (UDP payload and whole frame), plus the same rate over 5 minutes, the
    paper's run length, when the run's `duration` (default: first to last record) is known.
    """
    recs = list(records)
    if duration is None:
        times = [r.time for r in recs if r.kind == SDFR]
        duration = (max(times) - min(times)) if times else 0.0
    scale = FIVE_MINUTES_S / duration if duration > 0 else None
    robots: dict[str, Any] = {}
    for robot, t in traffic_per_robot(recs).items():
        entry: dict[str, Any] = {
            "tx": t.tx.to_json(),
            "rx": t.rx.to_json(),
            "tx_kB": {"payload": t.tx.payload_bytes / 1000, "frame": t.tx.frame_bytes / 1000},
            "rx_kB": {"payload": t.rx.payload_bytes / 1000, "frame": t.rx.frame_bytes / 1000},
        }
        if scale is not None:
            entry["per_5_min_kB"] = {
                f"{d}_{s}": round(entry[f"{d}_kB"][s] * scale, 3)
                for d in ("tx", "rx")
                for s in ("payload", "frame")
            }
        robots[robot] = entry
    return {
        "definition": (
            "TX: SDfR datagrams (UDP port 1900) a robot sent, by the robot id in them; RX: "
            "those that reached the robot's interface. payload = UDP payload bytes; frame = "
            "whole Ethernet frame as captured (headers included, no preamble/FCS). "
            "1 kB = 1000 bytes. ARP is not included."
        ),
        "duration_s": duration,
        "robots": robots,
        "paper_5_min_kB": {"tx": list(PAPER_TX_KB_5MIN), "rx": list(PAPER_RX_KB_5MIN)},
    }


def arp_counts(records: Iterable[Record]) -> ArpCounts:
    """ARP frames put on the air (`transmissions` of kind "arp"), by purpose.

    A probe has sender IP 0.0.0.0 (RFC 5227 2.1.1); an announcement has sender IP == target
    IP (2.3), as a request or a reply.
    """
    return _arp_tally(transmissions(records, kind=ARP))


def arp_counts_by_sender(records: Iterable[Record]) -> dict[str, ArpCounts]:
    """`arp_counts` per sender MAC address."""
    groups: dict[str, list[Record]] = defaultdict(list)
    for r in transmissions(records, kind=ARP):
        groups[r.src_mac].append(r)
    return {mac: _arp_tally(recs) for mac, recs in sorted(groups.items())}


def _arp_tally(records: Iterable[Record]) -> ArpCounts:
    counts = ArpCounts()
    for r in records:
        if r.src == "0.0.0.0":
            counts.probes += 1
        elif r.src == r.dst:
            counts.announcements += 1
        elif r.arp_op == 1:
            counts.requests += 1
        else:
            counts.replies += 1
    return counts


def count_updates(
    records: Iterable[Record],
    *,
    since: float = -math.inf,
    until: float = math.inf,
    robot: str | None = None,
) -> int:
    """Update datagrams sent in [since, until), by `robot` or by anyone; each datagram once.

    After a merge of partitions whose service sets did not change, this stays 0.
    """
    return sum(
        1
        for r in transmissions(records)
        if r.msg_type == "Update"
        and since <= r.time < until
        and (robot is None or r.robot == robot)
    )


@dataclass(frozen=True, slots=True)
class PingTally:
    """Unicast pings one robot sent another, and how many of their replies came back."""

    sent: int
    answered: int

    @property
    def rate(self) -> float | None:
        return self.answered / self.sent if self.sent else None


def ping_delivery(
    records: Iterable[Record], *, since: float = -math.inf, until: float = math.inf
) -> dict[tuple[str, str], PingTally]:
    """(pinger, pinged) -> pings the pinger sent in [since, until) and replies that reached
    it: the round-trip delivery the connection indicator estimates, measured on the air.
    A ping is a Discovery with a sequence number, or one riding on a ping reply (`ping`).
    Needs the robots' own captures (their "tx" and "rx" records)."""
    records = list(records)
    owners = _address_owners(records)
    sent: dict[tuple[str, int], str] = {}  # (capture, seq) -> pinged robot
    pinger: dict[str, str] = {}  # capture -> the robot whose pings it saw leave
    replies: set[tuple[str, int]] = set()
    for r in records:
        if r.kind != SDFR or r.seq is None:
            continue
        if r.direction == TX and since <= r.time < until:
            target = owners.get(r.dst)
            seq = r.seq if r.msg_type == "Discovery" else r.ping
            if target is not None and r.robot is not None and seq is not None:
                sent[(r.capture, seq)] = target
                pinger[r.capture] = r.robot
        elif r.direction == RX and r.msg_type == "Response":
            replies.add((r.capture, r.seq))
    answered = replies & set(sent)
    tally: dict[tuple[str, str], list[int]] = defaultdict(lambda: [0, 0])
    for (capture, seq), target in sent.items():
        t = tally[(pinger[capture], target)]
        t[0] += 1
        t[1] += (capture, seq) in answered
    return {pair: PingTally(n, ok) for pair, (n, ok) in sorted(tally.items())}


def neighbour_agreement(
    truth: Mapping[str, Iterable[str]], observed: Mapping[str, Iterable[str]]
) -> float:
    """Share of ordered robot pairs (a, b) on which a's neighbour list agrees with the truth.

    `truth[a]` holds the robots a can really hear now; `observed[a]` those a lists as
    reachable.  Robots are the keys of `truth`; 1.0 with fewer than two robots.
    """
    robots = sorted(truth)
    real = {a: set(truth[a]) for a in robots}
    seen = {a: set(observed.get(a, ())) for a in robots}
    pairs = agree = 0
    for a in robots:
        for b in robots:
            if a != b:
                pairs += 1
                agree += (b in real[a]) == (b in seen[a])
    return agree / pairs if pairs else 1.0


def _natural(key: str) -> tuple[Any, ...]:
    """Sort key putting r2 before r10."""
    out: list[Any] = []
    num = ""
    for ch in key:
        if ch.isdigit():
            num += ch
            continue
        if num:
            out.append((0, int(num), ""))
            num = ""
        out.append((1, 0, ch))
    if num:
        out.append((0, int(num), ""))
    return tuple(out)


def _sorted(items: Mapping[str, _T]) -> dict[str, _T]:
    return {k: items[k] for k in sorted(items, key=_natural)}


def natural_order(keys: Sequence[str]) -> list[str]:
    """Robot names in human order (r2 before r10)."""
    return sorted(keys, key=_natural)
