"""What `make bench-paper` makes of a run, as pure functions: bytes per robot from pcaps,
how long changes took to be seen, CPU and memory from process readings.

Nothing here starts anything; the driver (`bench.paper`) hands in files and readings, so
these are tested on synthetic pcaps and logs without root.
"""

from __future__ import annotations

import json
import math
import statistics
import struct
from collections import defaultdict
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from netlab.analysis import Totals

#: The paper's figures (section 6): its numbers, as the bench compares with them.
PAPER = {
    "publish_ms": (95.0, 130.0),
    "unpublish_ms": (98.0, 122.0),
    "neighbors_ms_max": 5.0,
    "cpu_percent": (2.2, 2.8),
    "memory_percent_of_4GB_max": 0.3,
    "tx_kB_5min": (220.0, 320.0),
    "rx_kB_5min": (540.0, 850.0),
}
#: 0.3 % of the paper's 4 GB robots, in MiB.
PAPER_MEMORY_MIB = PAPER["memory_percent_of_4GB_max"] / 100 * 4 * 1024  # type: ignore[operator]
FIVE_MINUTES_S = 300.0
#: The bound a change must be seen within on every peer (docs/fleet-behaviour.md, 6).
SEEN_WITHIN_S = 0.5

_PCAP_HEADER = struct.Struct("<IHHiIII")


@dataclass(slots=True)
class PortTraffic:
    """One robot's traffic on one port: what it sent (tx) and what reached it (rx)."""

    tx: Totals = field(default_factory=Totals)
    rx: Totals = field(default_factory=Totals)


def _frames(path: Path) -> Iterator[tuple[float, bytes, int]]:
    """(time, captured bytes, original length) of each record of a classic pcap."""
    data = path.read_bytes()
    if len(data) < _PCAP_HEADER.size:
        return
    magic = struct.unpack_from("<I", data)[0]
    if magic == 0xA1B2C3D4:
        order, frac = "<", 1e-6
    elif magic == 0xA1B23C4D:
        order, frac = "<", 1e-9
    elif magic == 0xD4C3B2A1:
        order, frac = ">", 1e-6
    elif magic == 0x4D3CB2A1:
        order, frac = ">", 1e-9
    else:
        raise ValueError(f"{path} is not a classic pcap file (magic {magic:#x})")
    header = struct.Struct(order + "IIII")
    link = struct.unpack_from(order + "I", data, 20)[0]
    if link != 1:
        raise ValueError(f"{path}: link type {link}, not Ethernet")
    at = _PCAP_HEADER.size
    while at + header.size <= len(data):
        sec, sub, caplen, origlen = header.unpack_from(data, at)
        at += header.size
        yield sec + sub * frac, data[at : at + caplen], origlen
        at += caplen


#: A transport and a port: ("udp", 5353), ("tcp", 7447).
Flow = tuple[str, int]
_PROTOCOLS = {17: "udp", 6: "tcp"}


def ip_traffic(
    pcap: Path, own_mac: str, flows: Sequence[Flow], window: tuple[float, float]
) -> dict[Flow, PortTraffic]:
    """Per flow (UDP or TCP and a port, as source or destination), what a robot's capture saw
    it send (source MAC its own) and receive in `window` (wall-clock seconds, the pcap's
    clock), IPv4 over Ethernet.  A frame's size is its original length (the whole frame, no
    FCS); its payload is the transport's (from the IP header's total length, so a frame cut
    short by the capture's snap length still counts whole).  A TCP segment counts as one
    datagram, pure ACKs included.  A UDP datagram the sender's IP fragmented (Fast DDS sends
    up to 64 kB at once) counts once, with its whole payload, when its first fragment is seen;
    its later fragments (which carry no UDP header, and which the capture must have kept:
    `capture_filter`) add their frames."""
    mac = bytes.fromhex(own_mac.replace(":", ""))
    out = {flow: PortTraffic() for flow in flows}
    start, end = window
    fragmented: dict[bytes, Totals] = {}  # source, destination, IP id, protocol -> its totals
    for t, frame, length in _frames(pcap):
        if not start <= t <= end or len(frame) < 42 or frame[12:14] != b"\x08\x00":
            continue
        proto = _PROTOCOLS.get(frame[23])
        ihl = (frame[14] & 0x0F) * 4
        at = 14 + ihl
        frag = struct.unpack_from("!H", frame, 20)[0]
        datagram = frame[26:34] + frame[18:20] + frame[23:24]
        if frag & 0x1FFF:  # a later fragment
            if datagram in fragmented:
                fragmented[datagram].fragment(length)
            continue
        if proto is None or len(frame) < at + (20 if proto == "tcp" else 8):
            continue
        sport, dport = struct.unpack_from("!HH", frame, at)
        flow = (proto, sport) if (proto, sport) in out else (proto, dport)
        if flow not in out:
            continue
        if proto == "udp":
            payload = struct.unpack_from("!H", frame, at + 4)[0] - 8
        else:
            total = struct.unpack_from("!H", frame, 16)[0]
            payload = total - ihl - (frame[at + 12] >> 4) * 4
        totals = out[flow].tx if frame[6:12] == mac else out[flow].rx
        totals.count(payload, length)
        if frag & 0x2000:  # more fragments follow
            fragmented[datagram] = totals
    return out


def udp_traffic(
    pcap: Path, own_mac: str, ports: Sequence[int], window: tuple[float, float]
) -> dict[int, PortTraffic]:
    """`ip_traffic` of these UDP ports, by port."""
    got = ip_traffic(pcap, own_mac, [("udp", port) for port in ports], window)
    return {port: got[("udp", port)] for port in ports}


def mdns_messages(pcap: Path, own_mac: str, window: tuple[float, float]) -> dict[str, int]:
    """mDNS (UDP 5353) messages a robot sent in `window`: queries and responses (the QR bit
    of the DNS header), and the responses' UDP payload bytes."""
    mac = bytes.fromhex(own_mac.replace(":", ""))
    out = {"queries": 0, "responses": 0, "response_bytes": 0}
    for t, frame, _ in _frames(pcap):
        if not window[0] <= t <= window[1] or frame[6:12] != mac or frame[12:14] != b"\x08\x00":
            continue
        ihl = (frame[14] & 0x0F) * 4
        at = 14 + ihl
        if frame[23] != 17 or len(frame) < at + 8 + 12:
            continue
        sport, dport, ulen = struct.unpack_from("!HHH", frame, at)
        if 5353 not in (sport, dport):
            continue
        if frame[at + 8 + 2] & 0x80:
            out["responses"] += 1
            out["response_bytes"] += ulen - 8
        else:
            out["queries"] += 1
    return out


def per_5_min(value: float, seconds: float) -> float:
    """`value` counted over `seconds`, as over 5 minutes."""
    return value * FIVE_MINUTES_S / seconds if seconds > 0 else math.nan


def percentiles(samples: Iterable[float]) -> dict[str, float | int]:
    """count, p50, p99, max and mean of `samples` (milliseconds in, milliseconds out)."""
    s = sorted(samples)
    if not s:
        return {"count": 0}

    def pct(p: float) -> float:
        return round(s[min(len(s) - 1, int(p / 100 * len(s)))], 3)

    return {
        "count": len(s),
        "p50_ms": pct(50),
        "p99_ms": pct(99),
        "max_ms": round(s[-1], 3),
        "mean_ms": round(statistics.fmean(s), 3),
    }


# -- how long changes took to be seen ------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Change:
    """A publish or unpublish, done (answered) at `t` on `robot`."""

    t: float
    robot: str
    sid: str
    op: str  # "publish" or "unpublish"


def read_events(paths: Iterable[Path]) -> list[dict[str, Any]]:
    """The JSON lines the load generators wrote (`bench.paper_load --events`), by time."""
    out: list[dict[str, Any]] = []
    for path in paths:
        with open(path) as f:
            for line in f:
                if line.strip():
                    out.append(json.loads(line))
    out.sort(key=lambda e: float(e["t"]))
    return out


def propagation(
    events: Sequence[Mapping[str, Any]],
    watchers: Iterable[str],
    *,
    until: float,
    since: float = -math.inf,
    linked: Any = None,
    bound: float = SEEN_WITHIN_S,
    start: str = "t",
) -> dict[str, Any]:
    """How long each change took to be seen by every other robot's watcher.

    A publish is seen at robot B when B's watcher first lists the service after it was done;
    an unpublish when B's watcher first no longer lists it.  Excluded, and counted: changes
    undone within `bound` (a publish unpublished again before it was seen: coalesced away,
    nothing to see), and changes less than `bound` + 1 s before `until` (the run's end);
    changes before `since` are not counted at all.
    `linked(a, b, t)`, when given, says whether b could hear a at `t` (a moving fleet):
    pairs that were not are left out.  A change's time is its `start` field: "t", when its
    request was answered (then latencies may be slightly negative: a peer can list a service
    before its publisher has read the answer), or "asked", when it was asked for.
    """
    watch = sorted(set(watchers))
    seen: dict[tuple[str, str, str], list[tuple[float, str]]] = defaultdict(list)
    changes: list[Change] = []
    undone: dict[str, float] = {}
    for e in events:
        op = e["op"]
        if op in ("seen", "gone"):
            seen[(str(e["at"]), str(e["robot"]), str(e["sid"]))].append((float(e["t"]), op))
        elif op in ("publish", "unpublish"):
            t = float(e.get(start, e["t"]))
            changes.append(Change(t, str(e["robot"]), str(e["sid"]), op))
            if op == "unpublish":
                undone[str(e["sid"])] = t
    lat: dict[str, list[float]] = {"publish": [], "unpublish": []}
    late: dict[str, int] = {"publish": 0, "unpublish": 0}
    never = {"publish": 0, "unpublish": 0}
    superseded = 0
    too_late = 0
    coalesced: set[str] = set()
    for c in changes:
        if c.t < since:
            continue
        if c.t > until - bound - 1.0:
            too_late += 1
            continue
        if c.sid in coalesced or (
            c.op == "publish" and c.sid in undone and undone[c.sid] - c.t < bound
        ):
            superseded += 1  # (its unpublish too: nobody listed it, nobody unlists it)
            coalesced.add(c.sid)
            continue
        want = "seen" if c.op == "publish" else "gone"
        for b in watch:
            if b == c.robot or (linked is not None and not linked(c.robot, b, c.t)):
                continue
            # The first observation of the wanted kind after the change was asked for (its
            # answer comes at c.t; a request takes well under a second here).
            obs = [t for t, kind in seen.get((b, c.robot, c.sid), ()) if kind == want]
            after = [t for t in obs if t >= c.t - 1.0]
            if not after:
                never[c.op] += 1
                continue
            dt = after[0] - c.t
            lat[c.op].append(dt * 1000)
            if dt > bound:
                late[c.op] += 1
    total = {op: len(v) + never[op] for op, v in lat.items()}
    return {
        "bound_ms": bound * 1000,
        "watchers": watch,
        "publish": {**percentiles(lat["publish"]), "late": late["publish"],
                    "never": never["publish"]},
        "unpublish": {**percentiles(lat["unpublish"]), "late": late["unpublish"],
                      "never": never["unpublish"]},
        "within_bound": {
            op: round(1 - (late[op] + never[op]) / total[op], 4) if total[op] else None
            for op in total
        },
        "excluded": {"undone_within_bound": superseded, "near_the_end": too_late},
    }  # fmt: skip


# -- CPU and memory ------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Reading:
    """One reading of a process tree (or one process): when, CPU seconds so far, PSS KiB."""

    time: float
    cpu_s: float
    pss_kb: int
    rss_kb: int = 0


def usage(readings: Sequence[Reading]) -> dict[str, Any]:
    """CPU as % of one core between the first and last reading; PSS mean and max (MiB)."""
    if len(readings) < 2:
        return {"samples": len(readings)}
    first, last = readings[0], readings[-1]
    wall = last.time - first.time
    pss = [r.pss_kb / 1024 for r in readings]
    return {
        "cpu_percent": round(100 * max(0.0, last.cpu_s - first.cpu_s) / wall, 2) if wall else None,
        "pss_mib_mean": round(statistics.fmean(pss), 1),
        "pss_mib_max": round(max(pss), 1),
        "rss_mib_max": round(max(r.rss_kb for r in readings) / 1024, 1),
        "samples": len(readings),
        "wall_s": round(wall, 1),
    }


def spread(values: Iterable[float], ndigits: int = 1) -> dict[str, float]:
    """min, max and mean of `values` (NaN ignored)."""
    v = [x for x in values if x is not None and not math.isnan(x)]
    if not v:
        return {}
    return {
        "min": round(min(v), ndigits),
        "max": round(max(v), ndigits),
        "mean": round(statistics.fmean(v), ndigits),
    }


def dig(d: Any, *keys: str) -> Any:
    """d[k1][k2]... of a result's JSON, None where a level is missing (a part that failed)."""
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d
