"""An outsider on a lab's medium, for the security tests and `bench.flood`: run inside a
namespace as ``python -m sdfr.testing.outsider COMMAND ...`` (netlab's ``lab.exec``/``lab.popen``).

It knows only the public wire format: it sends datagrams (hex on the command line) from its
own address or from any address it likes (a raw socket writes the IP header itself), captures
the robots' multicast datagrams to replay them, floods a robot with fake robots, and listens
as the victim of a reflection.

- ``send --to IP[:PORT] [--spoof IP[:PORT]] [--repeat N] [--interval S] HEX...``
- ``capture --kind KIND [--sender IP] [--count N] [--timeout S]``: prints one hex line per
  datagram received on the SDfR group that decodes as a message of KIND (``alive``,
  ``update``, ...: the message class, in either wire form) (from IP).
- ``flood --to IP --count N [--fleet F] [--net A.B] [--rate R --seconds S]``: N Alives of N
  fake robots, each from its own forged address in A.B.100.1 - A.B.249.250 (the lab's /16,
  away from its robots); with --rate, R a second for S seconds, cycling through them.
- ``listen --port P --timeout S``: prints JSON ``{"datagrams": n, "bytes": b, "sources":
  {ip: [n, b]}}`` received (in all, and by source address).

With ears: on a medium where every frame reaches every port (a radio; the attack tests make the
lab's bridge one), the outsider also hears the robots' unicasts to each other:

- ``record --out FILE [--iface IF] [--seconds S]``: every UDP datagram to or from port 1900
  on the interface (the robots' multicasts and unicasts) as JSON lines ``{"t", "src", "dst",
  "hex"}`` (``src``/``dst`` are ``ip:port``), until SIGTERM or S seconds; prints ``ready`` once
  it hears.
- ``replay --plan FILE``: sends datagrams on a timeline, one JSON line each ``{"at": seconds
  from the start, "hex", "to": "ip[:port]", "spoof": "ip[:port]" or null}``; prints one JSON
  line ``{"sent": i, "t": unix time}`` per datagram.
- ``relay --sender IP --to IP[:PORT] [--spoof IP[:PORT]] [--seconds S]``: sends each datagram
  heard from IP on to ``--to`` (from its own address, or from ``--spoof``) as it comes, for S
  seconds; prints ``ready``, then JSON ``{"relayed": n}``.
"""

from __future__ import annotations

import argparse
import json
import signal
import socket
import struct
import sys
import time
from collections.abc import Iterator

from sdfr import wire

GROUP = wire.DEFAULT_GROUP
PORT = wire.DEFAULT_PORT


def _addr(text: str) -> tuple[str, int]:
    host, _, port = text.partition(":")
    return host, int(port) if port else PORT


def _udp_packet(src: tuple[str, int], dst: tuple[str, int], payload: bytes, ttl: int) -> bytes:
    """An IPv4 + UDP packet; the kernel fills in the IP checksum, the UDP one is left 0."""
    udp = struct.pack("!HHHH", src[1], dst[1], 8 + len(payload), 0) + payload
    ip = struct.pack(
        "!BBHHHBBH4s4s",
        0x45,
        0,
        20 + len(udp),
        0,
        0x4000,
        ttl,
        socket.IPPROTO_UDP,
        0,
        socket.inet_aton(src[0]),
        socket.inet_aton(dst[0]),
    )
    return ip + udp


class Sender:
    def __init__(self) -> None:
        self.raw = socket.socket(socket.AF_INET, socket.SOCK_RAW, socket.IPPROTO_RAW)
        self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.udp.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)

    def send(self, data: bytes, dst: tuple[str, int], spoof: tuple[str, int] | None) -> None:
        if spoof is None:
            self.udp.sendto(data, dst)
        else:
            ttl = 1 if dst[0] == GROUP else 64
            self.raw.sendto(_udp_packet(spoof, dst, data, ttl), (dst[0], 0))


def cmd_send(args: argparse.Namespace) -> int:
    sender = Sender()
    dst = _addr(args.to)
    spoof = _addr(args.spoof) if args.spoof else None
    datagrams = [bytes.fromhex(h) for h in args.hex]
    for i in range(args.repeat):
        for data in datagrams:
            sender.send(data, dst, spoof)
        if i + 1 < args.repeat:
            time.sleep(args.interval)
    return 0


def _received(sock: socket.socket, timeout: float) -> Iterator[tuple[bytes, tuple[str, int]]]:
    """The datagrams `sock` receives until `timeout` seconds from now."""
    deadline = time.monotonic() + timeout
    while (left := deadline - time.monotonic()) > 0:
        sock.settimeout(left)
        try:
            data, src = sock.recvfrom(4096)
        except TimeoutError:
            return
        yield data, src


def cmd_capture(args: argparse.Namespace) -> int:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("", PORT))
    mreq = struct.pack("4s4s", socket.inet_aton(GROUP), socket.inet_aton("0.0.0.0"))
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
    found = 0
    for data, src in _received(sock, args.timeout):
        kind = type(wire.decode(data)).__name__.lower()
        if kind == args.kind and (args.sender is None or src[0] == args.sender):
            print(data.hex(), flush=True)
            found += 1
            if found >= args.count:
                return 0
    return 1


def cmd_flood(args: argparse.Namespace) -> int:
    sender = Sender()
    dst = _addr(args.to)
    a, b = (int(x) for x in args.net.split("."))
    fakes = []
    for i in range(args.count):
        origin = wire.Origin(args.fleet, f"fake{i}", 1, 1, "0" * 16)
        data = wire.encode(wire.Alive(origin, "http://10.0.0.1/", 30))
        fakes.append((data, (f"{a}.{b}.{100 + i // 250 % 150}.{i % 250 + 1}", PORT)))
    if args.rate is None:  # as fast as it goes, each fake once
        for data, src in fakes:
            sender.send(data, dst, src)
        print(json.dumps({"sent": len(fakes)}), flush=True)
        return 0
    # Paced: `rate` a second for `seconds`, cycling through the fakes, in 10 ms batches.
    start = time.monotonic()
    sent = 0
    while (now := time.monotonic() - start) < args.seconds:
        due = int(now * args.rate) + 1
        while sent < due:
            data, src = fakes[sent % len(fakes)]
            sender.send(data, dst, src)
            sent += 1
        time.sleep(0.01)
    print(json.dumps({"sent": sent, "seconds": round(time.monotonic() - start, 3)}), flush=True)
    return 0


def cmd_listen(args: argparse.Namespace) -> int:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("", args.port))
    count = total = 0
    sources: dict[str, list[int]] = {}
    for data, src in _received(sock, args.timeout):
        count += 1
        total += len(data)
        seen = sources.setdefault(src[0], [0, 0])
        seen[0] += 1
        seen[1] += len(data)
    print(json.dumps({"datagrams": count, "bytes": total, "sources": sources}), flush=True)
    return 0


# -- ears: a packet socket hears every frame that reaches the interface --------------------

ETH_P_IP = 0x0800
PACKET_OUTGOING = 4  # sll_pkttype of a frame this host sent
SOL_PACKET = 263
PACKET_ADD_MEMBERSHIP = 1
PACKET_MR_PROMISC = 1


def _ears(iface: str) -> socket.socket:
    """A packet socket on `iface` in promiscuous mode: frames for other hosts too."""
    sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_IP))
    sock.bind((iface, ETH_P_IP))
    mreq = struct.pack("iHH8s", socket.if_nametoindex(iface), PACKET_MR_PROMISC, 0, b"")
    sock.setsockopt(SOL_PACKET, PACKET_ADD_MEMBERSHIP, mreq)
    return sock


def udp_of(frame: bytes) -> tuple[tuple[str, int], tuple[str, int], bytes] | None:
    """(source, destination, payload) of an Ethernet frame carrying a whole IPv4 UDP
    datagram; None for anything else."""
    if len(frame) < 14 + 20 + 8 or frame[12:14] != b"\x08\x00":
        return None
    ip = frame[14:]
    ihl = (ip[0] & 0x0F) * 4
    total = struct.unpack("!H", ip[2:4])[0]
    frag = struct.unpack("!H", ip[6:8])[0]
    if ip[0] >> 4 != 4 or ip[9] != socket.IPPROTO_UDP or frag & 0x3FFF or total > len(ip):
        return None
    udp = ip[ihl:total]
    sport, dport, length = struct.unpack("!HHH", udp[:6])
    src, dst = socket.inet_ntoa(ip[12:16]), socket.inet_ntoa(ip[16:20])
    return (src, sport), (dst, dport), udp[8:length]


class _Stop:
    """SIGTERM/SIGINT end a long-running command cleanly (its output flushed)."""

    def __init__(self) -> None:
        self.asked = False
        signal.signal(signal.SIGTERM, self._ask)
        signal.signal(signal.SIGINT, self._ask)

    def _ask(self, *_: object) -> None:
        self.asked = True


def _heard(
    sock: socket.socket, seconds: float, stop: _Stop
) -> Iterator[tuple[tuple[str, int], tuple[str, int], bytes]]:
    """UDP datagrams to or from the SDfR port that others sent, until `seconds` or a stop."""
    deadline = time.monotonic() + seconds
    sock.settimeout(0.1)
    while not stop.asked and time.monotonic() < deadline:
        try:
            frame, addr = sock.recvfrom(65535)
        except (TimeoutError, InterruptedError):
            continue
        if addr[2] == PACKET_OUTGOING:
            continue
        got = udp_of(frame)
        if got is not None and PORT in (got[0][1], got[1][1]):
            yield got


def _text(addr: tuple[str, int]) -> str:
    return f"{addr[0]}:{addr[1]}"


def cmd_record(args: argparse.Namespace) -> int:
    stop = _Stop()
    sock = _ears(args.iface)
    print("ready", flush=True)
    with open(args.out, "w") as out:
        for src, dst, data in _heard(sock, args.seconds, stop):
            line = {"t": time.time(), "src": _text(src), "dst": _text(dst), "hex": data.hex()}
            out.write(json.dumps(line) + "\n")
            out.flush()
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    with open(args.plan) as f:
        plan = [json.loads(line) for line in f if line.strip()]
    sender = Sender()
    start = time.monotonic()
    for i, step in enumerate(plan):
        wait = start + float(step["at"]) - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        spoof = _addr(step["spoof"]) if step.get("spoof") else None
        sender.send(bytes.fromhex(step["hex"]), _addr(step["to"]), spoof)
        print(json.dumps({"sent": i, "t": time.time()}), flush=True)
    return 0


def cmd_relay(args: argparse.Namespace) -> int:
    stop = _Stop()
    sock = _ears(args.iface)
    sender = Sender()
    dst = _addr(args.to)
    spoof = _addr(args.spoof) if args.spoof else None
    if spoof is not None and spoof[0] == args.sender:
        raise SystemExit("relay: --spoof must not be the sender (it would hear itself)")
    print("ready", flush=True)
    relayed = 0
    for src, _, data in _heard(sock, args.seconds, stop):
        if src[0] == args.sender:
            sender.send(data, dst, spoof)
            relayed += 1
    print(json.dumps({"relayed": relayed}), flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="outsider")
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("send")
    s.add_argument("--to", required=True)
    s.add_argument("--spoof")
    s.add_argument("--repeat", type=int, default=1)
    s.add_argument("--interval", type=float, default=1.0)
    s.add_argument("hex", nargs="+")
    s.set_defaults(fn=cmd_send)
    c = sub.add_parser("capture")
    c.add_argument("--kind", required=True)
    c.add_argument("--sender")
    c.add_argument("--count", type=int, default=1)
    c.add_argument("--timeout", type=float, default=5.0)
    c.set_defaults(fn=cmd_capture)
    f = sub.add_parser("flood")
    f.add_argument("--to", required=True)
    f.add_argument("--count", type=int, required=True)
    f.add_argument("--fleet", type=int, default=1)
    f.add_argument("--net", default="10.77")
    f.add_argument("--rate", type=float, help="datagrams a second (default: as fast as it goes)")
    f.add_argument("--seconds", type=float, default=10.0, help="how long, with --rate")
    f.set_defaults(fn=cmd_flood)
    listen = sub.add_parser("listen")
    listen.add_argument("--port", type=int, default=PORT)
    listen.add_argument("--timeout", type=float, default=3.0)
    listen.set_defaults(fn=cmd_listen)
    r = sub.add_parser("record")
    r.add_argument("--out", required=True)
    r.add_argument("--iface", default="eth0")
    r.add_argument("--seconds", type=float, default=600.0)
    r.set_defaults(fn=cmd_record)
    p_replay = sub.add_parser("replay")
    p_replay.add_argument("--plan", required=True)
    p_replay.set_defaults(fn=cmd_replay)
    relay = sub.add_parser("relay")
    relay.add_argument("--sender", required=True)
    relay.add_argument("--to", required=True)
    relay.add_argument("--spoof")
    relay.add_argument("--iface", default="eth0")
    relay.add_argument("--seconds", type=float, default=10.0)
    relay.set_defaults(fn=cmd_relay)
    args = p.parse_args(argv)
    code: int = args.fn(args)
    return code


if __name__ == "__main__":
    sys.exit(main())
