"""The floor under every discovery system's figures: a bare multicast datagram's one-way time
from one robot to another on the lab's medium, from the sender's program to the receiver's.

No discovery system can tell a change faster than this.  The robots of a lab share the host's
clock, so the sender's time in each datagram and the receiver's time at its arrival make the
one-way time.  `measure` runs both ends in a lab; the receiver also runs alone:

    python -m bench.floor recv --ip IP --count N --out FILE
    python -m bench.floor send --ip IP --count N
"""

from __future__ import annotations

import argparse
import json
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from bench.load import summary
from bench.paper_lab import ROOT

GROUP = "239.255.77.77"
PORT = 19077
GAP_S = 0.01  # between datagrams: no queueing behind each other


def _recv(ip: str, count: int, out: Path, timeout: float) -> None:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("", PORT))
    group = socket.inet_aton(GROUP) + socket.inet_aton(ip)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, group)
    sock.settimeout(timeout)
    print("ready", flush=True)
    took: list[float] = []
    try:
        while len(took) < count:
            data = sock.recv(64)
            now = time.time()
            took.append(now - struct.unpack("!d", data[:8])[0])
    except TimeoutError:
        pass
    out.write_text(json.dumps(took))


def _send(ip: str, count: int) -> None:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(ip))
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
    for _ in range(count):
        sock.sendto(struct.pack("!d", time.time()) + b"\0" * 56, (GROUP, PORT))
        time.sleep(GAP_S)


def measure(lab: Any, sender: str, receiver: str, folder: Path, count: int = 200) -> dict[str, Any]:
    """`count` datagrams from `sender` to `receiver` in `lab`: their one-way time (ms: p50,
    p90, p99, max, mean; none when none arrived) and how many arrived."""
    out = folder / f"floor-{sender}-{receiver}.json"
    argv = [sys.executable, "-m", "bench.floor"]
    rx = lab.popen(receiver, [*argv, "recv", "--ip", lab.robot(receiver).ip,
                              "--count", str(count), "--out", str(out)],
                   cwd=str(ROOT), stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        if rx.stdout.readline().strip() != "ready":
            raise RuntimeError(f"the floor's receiver on {receiver} did not start")
        send = [*argv, "send", "--ip", lab.robot(sender).ip, "--count", str(count)]
        sent = lab.exec(sender, send, cwd=str(ROOT), timeout=60 + count * GAP_S)
        if sent.returncode != 0:
            raise RuntimeError(f"the floor's sender on {sender} failed: {sent.stderr[-500:]}")
        rx.wait(timeout=30)
    finally:
        if rx.poll() is None:
            rx.kill()
            rx.wait()
    took: list[float] = json.loads(out.read_text()) if out.exists() else []
    times = {k: v for k, v in summary(took).items() if k != "count"}  # p50_ms, p99_ms, max_ms...
    return {"sent": count, "arrived": len(took), **times, "from": sender, "to": receiver}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("role", choices=("recv", "send"))
    p.add_argument("--ip", required=True, help="this robot's address on the medium")
    p.add_argument("--count", type=int, default=200)
    p.add_argument("--out", type=Path, help="recv: where the one-way times go (JSON, seconds)")
    p.add_argument("--timeout", type=float, default=10.0, help="recv: silence that ends it")
    args = p.parse_args(argv)
    if args.role == "recv":
        if args.out is None:
            p.error("recv needs --out")
        _recv(args.ip, args.count, args.out, args.timeout)
    else:
        _send(args.ip, args.count)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
