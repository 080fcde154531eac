"""Figures made from captured records (`netlab.pcap.Record`): pure functions, tested with
synthetic pcaps and no root.

Who sent, who received:

* sent datagrams (`transmissions`) are the ``tx`` records when there are any, else the records
  without a direction (a medium capture, or pcaps without metadata): each datagram once;
* a robot's received datagrams are the ``rx`` records of its own capture: what reached its
  interface (after the medium's loss), whether or not the daemon accepted it.

Senders are named by the robot id in the datagram; receivers by their capture's owner, the
robot whose datagrams that capture sent (falling back to the capture's label).

Sizes: ``payload_bytes`` sums the UDP payloads, ``frame_bytes`` the whole frames as captured
(see `netlab.pcap`); 1 kB = 1000 bytes.  ARP is counted apart (`arp_counts`), and so is what a
radio medium put on the air (`air_use`: 802.11 management, control, EAPOL and data frames).
"""

from __future__ import annotations

import math
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

from netlab.pcap import ARP, EAPOL, RX, SDFR, TX, WIFI_CTRL, WIFI_KINDS, WIFI_MGMT, Record

__all__ = [
    "AIR_KINDS",
    "ArpCounts",
    "PingTally",
    "RobotTraffic",
    "Series",
    "Totals",
    "air_use",
    "arp_counts",
    "arp_counts_by_sender",
    "capture_owners",
    "count_updates",
    "natural_order",
    "per_second",
    "per_type",
    "ping_delivery",
    "received_per_robot",
    "receptions",
    "rejects",
    "sent_per_robot",
    "traffic_per_robot",
    "transmissions",
]

_T = TypeVar("_T")


@dataclass(slots=True)
class Totals:
    """Datagrams and their bytes, summed."""

    datagrams: int = 0
    payload_bytes: int = 0
    frame_bytes: int = 0

    def add(self, rec: Record) -> None:
        self.count(rec.payload_len, rec.frame_len)

    def count(self, payload: int, frame: int) -> None:
        """One datagram more: `payload` bytes of UDP payload in a `frame`-byte frame."""
        self.datagrams += 1
        self.payload_bytes += payload
        self.frame_bytes += frame

    def fragment(self, frame: int) -> None:
        """A later IP fragment of a datagram counted already: only its `frame` bytes."""
        self.frame_bytes += frame

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


# ---------------------------------------------------------------------------------------------
# The air of a radio medium

#: What `air_use` counts apart: 802.11's frame types, EAPOL (the key handshake) out of data.
AIR_KINDS = ("management", "control", "eapol", "data")


def _air_kind(kind: str) -> str:
    return {WIFI_MGMT: "management", WIFI_CTRL: "control", EAPOL: "eapol"}.get(kind, "data")


def air_use(records: Iterable[Record], robots: Mapping[str, str] | None = None) -> dict[str, Any]:
    """What went on the air of a radio medium, in frames and bytes of 802.11 frames: in all,
    by kind (`AIR_KINDS`) and by transmitter.

    Only captures holding 802.11 frames count (a radio lab's medium capture, where each frame
    is seen once); their data frames are SDfR's datagrams among others, encrypted.  A
    transmitter is named by `robots` (radio MAC -> robot), else by its MAC; frames with no
    transmitter address (ACKs, CTS) are counted under "".  Empty when no capture has 802.11
    frames (a wired lab).
    """
    recs = list(records)
    air = {r.capture for r in recs if r.kind in WIFI_KINDS}
    names = {mac.lower(): robot for mac, robot in (robots or {}).items()}

    def tally() -> dict[str, Any]:
        return {
            "frames": 0,
            "bytes": 0,
            "by_kind": {k: {"frames": 0, "bytes": 0} for k in AIR_KINDS},
        }

    out = tally()
    by_sender: dict[str, dict[str, Any]] = {}
    for r in recs:
        if r.capture not in air:
            continue
        sender = names.get(r.src_mac, r.src_mac)
        kind = _air_kind(r.kind)
        for t in (out, by_sender.setdefault(sender, tally())):
            t["frames"] += 1
            t["bytes"] += r.frame_len
            t["by_kind"][kind]["frames"] += 1
            t["by_kind"][kind]["bytes"] += r.frame_len
    if not air:
        return {}
    out["by_transmitter"] = {k: by_sender[k] for k in natural_order(list(by_sender))}
    return out
