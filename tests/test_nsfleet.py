"""The namespace harness itself: reachability, multicast, link cuts, teardown."""

from __future__ import annotations

import os
import queue
import shutil
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable
from typing import Any

import pytest
from pyroute2 import netns

from sdfr import procfs
from tests.nsfleet import NsFleet, unique_name

pytestmark = pytest.mark.root

GROUP, PORT = "239.255.255.250", 1900

RECEIVER = r"""
import socket, struct, sys
group, port = sys.argv[1], int(sys.argv[2])
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
s.bind(("0.0.0.0", port))
mreq = struct.pack("4s4si", socket.inet_aton(group), socket.inet_aton("0.0.0.0"),
                   socket.if_nametoindex("eth0"))
s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
print("ready", flush=True)
while True:
    data, (host, _) = s.recvfrom(2048)
    print(host, data.decode(errors="replace"), flush=True)
"""

# No IP_MULTICAST_IF: the harness's 224.0.0.0/4 route must be enough.
SENDER = r"""
import socket, sys, time
group, port, message, count = sys.argv[1], int(sys.argv[2]), sys.argv[3], int(sys.argv[4])
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
for _ in range(count):
    s.sendto(message.encode(), (group, port))
    time.sleep(0.05)
"""


class Lines:
    """Collects a process's stdout lines on a thread, to wait on with a deadline."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stdout is not None
        self._q: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        stdout = proc.stdout
        threading.Thread(target=self._pump, args=(stdout,), daemon=True).start()

    def _pump(self, stdout: Any) -> None:
        for line in stdout:
            self._q.put(line.rstrip("\n"))

    def wait_for(self, pred: Callable[[str], bool], timeout: float) -> str | None:
        for line in self.seen:
            if pred(line):
                return line
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            try:
                line = self._q.get(timeout=left)
            except queue.Empty:
                break
            self.seen.append(line)
            if pred(line):
                return line
        return None


def receiver(fleet: NsFleet, i: int) -> Lines:
    proc = fleet.popen(
        i, [sys.executable, "-c", RECEIVER, GROUP, str(PORT)], stdout=subprocess.PIPE, text=True
    )
    lines = Lines(proc)
    assert lines.wait_for(lambda s: s == "ready", 10), f"receiver in r{i} did not start"
    return lines


def send(fleet: NsFleet, i: int, message: str, count: int = 3) -> None:
    done = fleet.exec(i, [sys.executable, "-c", SENDER, GROUP, str(PORT), message, str(count)])
    assert done.returncode == 0, done.stderr


def got(lines: Lines, fleet: NsFleet, sender: int, message: str, timeout: float) -> bool:
    expected = f"{fleet.address(sender)} {message}"
    return lines.wait_for(lambda s: s == expected, timeout) is not None


def test_layout(nsfleet_factory: Callable[..., NsFleet]) -> None:
    fleet = nsfleet_factory(3)
    assert set(fleet.namespaces) <= set(netns.listnetns())
    for i in (1, 2, 3):
        out = fleet.exec(i, ["ip", "-o", "addr", "show", "dev", "eth0"]).stdout
        assert f"inet {fleet.address(i)}/16" in out
        link = fleet.exec(i, ["ip", "-o", "link", "show", "dev", "eth0"]).stdout
        assert f"link/ether 02:00:00:00:00:0{i}" in link
        routes = fleet.exec(i, ["ip", "route", "show", "224.0.0.0/4"]).stdout
        assert "dev eth0" in routes
    per_robot = fleet.setup_seconds / fleet.n
    print(f"\nnamespace set-up: {per_robot * 1000:.1f} ms per robot")
    assert per_robot < 1.0


def test_custom_macs(nsfleet_factory: Callable[..., NsFleet]) -> None:
    macs = ["02:aa:00:00:00:01", "02:aa:00:00:00:02"]
    fleet = nsfleet_factory(2, macs=macs, subnet="10.7.0.0/16")
    link = fleet.exec(2, ["ip", "-o", "link", "show", "dev", "eth0"]).stdout
    assert "link/ether 02:aa:00:00:00:02" in link
    assert fleet.address(2) == "10.7.0.2"


@pytest.mark.skipif(
    shutil.which("ping") is None, reason="ping missing (scripts/bootstrap.sh installs it)"
)
def test_ping_all_pairs(nsfleet_factory: Callable[..., NsFleet]) -> None:
    fleet = nsfleet_factory(3)
    for i in (1, 2, 3):
        for j in (1, 2, 3):
            if i != j:
                done = fleet.exec(i, ["ping", "-c1", "-W1", fleet.address(j)])
                assert done.returncode == 0, f"r{i} -> r{j}: {done.stdout}{done.stderr}"


def test_multicast_cut_and_restore(nsfleet_factory: Callable[..., NsFleet]) -> None:
    fleet = nsfleet_factory(3)
    r2, r3 = receiver(fleet, 2), receiver(fleet, 3)

    hello = f"hello-{uuid.uuid4().hex[:8]}"
    send(fleet, 1, hello)
    assert got(r2, fleet, 1, hello, 5), f"r2 got {r2.seen}"
    assert got(r3, fleet, 1, hello, 5), f"r3 got {r3.seen}"

    fleet.cut(2)
    cut = f"cut-{uuid.uuid4().hex[:8]}"
    send(fleet, 1, cut)
    assert got(r3, fleet, 1, cut, 5), "r3 must still hear r1 while r2 is cut"
    assert not got(r2, fleet, 1, cut, 1.0), "r2 heard r1 through a cut link"

    fleet.restore(2)
    back = f"back-{uuid.uuid4().hex[:8]}"
    deadline = time.monotonic() + 10
    heard = False
    while not heard and time.monotonic() < deadline:
        send(fleet, 1, back, count=1)
        heard = got(r2, fleet, 1, back, 0.5)
    assert heard, f"r2 did not hear r1 after restore: {r2.seen}"
    # The message sent during the cut was lost, not delayed.
    assert not any(cut in line for line in r2.seen)


def test_teardown_removes_namespaces_and_processes() -> None:
    with NsFleet(unique_name(), 3) as fleet:
        name = fleet.name
        plain = fleet.popen(1, ["sleep", "300"])
        # A process that ignores SIGTERM, and one that left its group and session.
        stubborn = fleet.popen(
            2, [sys.executable, "-c", "import signal,time; signal.signal(15, 1); time.sleep(300)"]
        )
        escaper = fleet.popen(
            3, ["sh", "-c", "setsid sleep 300 & echo $!; wait"], stdout=subprocess.PIPE, text=True
        )
        assert escaper.stdout is not None
        escaped_pid = int(escaper.stdout.readline())
        assert os.path.exists(f"/proc/{escaped_pid}")
        time.sleep(0.2)  # let python install its signal handler
    assert not [ns for ns in netns.listnetns() if ns.startswith(name)]
    assert plain.returncode is not None
    assert stubborn.returncode is not None
    assert escaper.returncode is not None
    assert not _alive(escaped_pid)


def test_failed_setup_leaves_nothing() -> None:
    name = unique_name()
    # A multicast MAC is refused by the kernel when robot 2 is set up.
    fleet = NsFleet(name, 3, macs=["02:00:00:00:00:01", "01:00:5e:00:00:01", "02:00:00:00:00:03"])
    with pytest.raises(Exception), fleet:  # noqa: B017 - any set-up error will do
        pass
    assert not [ns for ns in netns.listnetns() if ns.startswith(name)]


def test_existing_namespace_is_not_touched() -> None:
    name = unique_name()
    netns.create(f"{name}-air")
    try:
        with pytest.raises(FileExistsError), NsFleet(name, 1):
            pass
        assert f"{name}-air" in netns.listnetns()
        assert f"{name}-r1" not in netns.listnetns()
    finally:
        netns.remove(f"{name}-air")


_alive = procfs.running
