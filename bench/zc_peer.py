"""A python-zeroconf robot doing what sdfrd does in bench.footprint: it publishes N services
(mDNS/DNS-SD, with TXT attributes) and keeps the list of the other robots' services (a
ServiceBrowser that resolves each one it hears of). Run inside a robot's namespace; it writes
what it lists to --status every second, and unregisters its services on SIGTERM.

    python -m bench.zc_peer --robot r1 --address 10.1.0.1 --services 10 --status FILE
"""

from __future__ import annotations

import argparse
import json
import signal
import socket
import threading
import time
from pathlib import Path

from zeroconf import IPVersion, ServiceBrowser, ServiceInfo, ServiceListener, Zeroconf

TYPE = "_sdfr-bench._tcp.local."


class Listing(ServiceListener):
    """The services of other robots, resolved (robot -> names)."""

    def __init__(self, robot: str) -> None:
        self.robot = robot
        self.found: dict[str, set[str]] = {}
        self.lock = threading.Lock()

    def _resolve(self, zc: Zeroconf, type_: str, name: str) -> None:
        info = zc.get_service_info(type_, name, timeout=3000)
        if info is None:
            return
        robot = ((info.properties or {}).get(b"robot") or b"").decode()
        if robot and robot != self.robot:
            with self.lock:
                self.found.setdefault(robot, set()).add(name)

    def add_service(self, zc: Zeroconf, type_: str, name: str) -> None:
        self._resolve(zc, type_, name)

    def update_service(self, zc: Zeroconf, type_: str, name: str) -> None:
        self._resolve(zc, type_, name)

    def remove_service(self, zc: Zeroconf, type_: str, name: str) -> None:
        with self.lock:
            for names in self.found.values():
                names.discard(name)

    def snapshot(self) -> dict[str, int]:
        with self.lock:
            return {robot: len(names) for robot, names in self.found.items() if names}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--robot", required=True)
    p.add_argument("--address", required=True, help="this robot's address (the interface)")
    p.add_argument("--services", type=int, default=10)
    p.add_argument("--status", type=Path, required=True)
    args = p.parse_args(argv)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    zc = Zeroconf(interfaces=[args.address], ip_version=IPVersion.V4Only)
    infos = [
        ServiceInfo(
            TYPE,
            f"{args.robot} service {k}.{TYPE}",
            addresses=[socket.inet_aton(args.address)],
            port=9000 + k,
            properties={"robot": args.robot, "fps": "30", "index": str(k)},
            server=f"{args.robot}.local.",
        )
        for k in range(args.services)
    ]
    listing = Listing(args.robot)
    browser = ServiceBrowser(zc, TYPE, listing)
    try:
        for info in infos:
            zc.register_service(info)
        while not stop.wait(1.0):
            tmp = args.status.with_suffix(".tmp")
            tmp.write_text(json.dumps({"at": time.time(), "robots": listing.snapshot()}))
            tmp.replace(args.status)
    finally:
        browser.cancel()
        zc.unregister_all_services()
        zc.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
