"""An outsider on a lab's medium, for the security tests: run inside a namespace as
``python -m tests.support.outsider COMMAND ...`` (netlab's ``lab.exec``/``lab.popen``).

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
- ``listen --port P --timeout S``: prints JSON ``{"datagrams": n, "bytes": b}`` received.
"""

from __future__ import annotations

import argparse
import json
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
    for data, _ in _received(sock, args.timeout):
        count += 1
        total += len(data)
    print(json.dumps({"datagrams": count, "bytes": total}), flush=True)
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
    args = p.parse_args(argv)
    code: int = args.fn(args)
    return code


if __name__ == "__main__":
    sys.exit(main())
