"""Captures of real `sdfrd` daemons in namespaces, and their analysis (needs root)."""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("scapy")

from netlab import analysis, naming, paper, pcap
from netlab.capture import Capture, CaptureError, CaptureInfo, sidecar_path, start_all, stop_all
from netlab.lab import Lab
from netlab.report import write_report
from sdfr.host import procfs

pytestmark = pytest.mark.root

FleetFactory = Callable[..., Lab]

BEACON = 0.5
ROBOTS = (1, 2, 3)
RUN_S = 3.0


def gone(pid: int) -> bool:
    """True when `pid` no longer runs (reaped, or a zombie nobody waits for)."""
    return not procfs.running(pid)


def neigh_overflows() -> int:
    """How often the kernel's IPv4 neighbour table was full, machine-wide (all namespaces
    share it: a big lab running at the same time can make every send fail with ENOBUFS)."""
    try:
        lines = Path("/proc/net/stat/arp_cache").read_text().split("\n")
    except OSError:
        return 0
    col = lines[0].split().index("table_fulls")
    return sum(int(line.split()[col], 16) for line in lines[1:] if line.strip())


def environment(before: int) -> str:
    """A hint for a failure message when the neighbour table overflowed during the test."""
    grew = neigh_overflows() - before
    if grew <= 0:
        return ""
    return (
        f" -- the kernel's neighbour table overflowed {grew} times during the test (shared by "
        "every namespace: another large lab is running?); raise "
        "net.ipv4.neigh.default.gc_thresh3"
    )


def ns(lab: Lab, i: int) -> str:
    return lab.robot(f"r{i}").ns


def test_captures_of_three_daemons(fleet_factory: FleetFactory, tmp_path: Path) -> None:
    overflows = neigh_overflows()
    lab = fleet_factory(len(ROBOTS), start=False)
    run = tmp_path / "run"
    caps = [Capture(ns(lab, i), naming.ROBOT_IFACE, run / f"r{i}.pcap") for i in ROBOTS]
    caps.append(Capture(lab.medium.ns, naming.BRIDGE, run / "air.pcap", label="air"))
    start_all(caps)
    try:
        assert all(c.running for c in caps)
        lab.start_all(beacon_interval=BEACON)
        time.sleep(RUN_S)  # traffic to capture, not a readiness wait
    finally:
        stats = stop_all(caps)
    pids = [c.pid for c in caps]
    assert all(p is not None and gone(p) for p in pids)
    assert not any(c.running for c in caps)
    assert all(s.captured and s.dropped == 0 for s in stats), f"{stats}{environment(overflows)}"

    # The sidecars say what each capture is.
    infos = {c.label: CaptureInfo.from_json(_json(sidecar_path(c.path))) for c in caps}
    assert infos["air"].role == "medium" and infos["air"].netns == lab.medium.ns
    for i in ROBOTS:
        info, robot = infos[f"r{i}"], lab.robot(f"r{i}")
        assert (info.role, info.iface, info.mac) == ("robot", naming.ROBOT_IFACE, robot.mac)
        assert str(robot.address) in info.addresses
        assert info.started is not None and info.stopped is not None
        assert info.stats.captured is not None and info.stats.captured > 0

    records = pcap.read_run(run)
    names = {f"r{i}" for i in ROBOTS}

    # Every robot beacons: Alive datagrams of a few hundred bytes.
    sent = analysis.transmissions(records)
    for robot in names:
        alive = [r for r in sent if r.robot == robot and r.msg_type == "Alive"]
        assert len(alive) >= 2, f"{robot}: {len(alive)} Alive datagrams"
        assert all(r.multicast and r.dst == "239.255.255.250" for r in alive)
        # (a wire-2 fleet's compact beacons: about 90 bytes; full ones 400-500)
        assert all(60 <= r.payload_len <= 700 for r in alive), [r.payload_len for r in alive]
        assert all(r.frame_len == r.payload_len + 42 for r in alive)
    assert not analysis.rejects(records)

    # TX of the three robots (from their own captures), RX of each from the two others.
    tx = analysis.sent_per_robot(records)
    rx = analysis.received_per_robot(records)
    assert set(tx) == names and set(rx) == names
    for robot in names:
        assert tx[robot].datagrams >= 2 and tx[robot].payload_bytes >= 400
        assert tx[robot].frame_bytes > tx[robot].payload_bytes
        assert rx[robot].datagrams >= 2
    r1_rx = {r.robot for r in analysis.receptions(records) if r.capture == "r1"}
    assert r1_rx == {"r2", "r3"}

    # The medium sees every robot, and each datagram the robots sent (up to shortly before
    # the captures stopped: the last frames may be in one capture and not yet in another).
    air = [r for r in records if r.capture == "air"]
    assert {r.robot for r in air if r.kind == "sdfr"} == names
    cutoff = min(i.stopped for i in infos.values() if i.stopped is not None) - 0.3
    air_sent = analysis.sent_per_robot(r for r in air if r.time < cutoff)
    robots_sent = analysis.sent_per_robot(r for r in records if r.time < cutoff)
    assert {k: v.to_json() for k, v in air_sent.items()} == {
        k: v.to_json() for k, v in robots_sent.items()
    }

    m = paper.paper_measure(records)
    assert set(m["robots"]) == names and m["duration_s"] > 1.0
    report = write_report(run, records=None, meta={"test": "ns"})
    assert report["traffic"]["robots"]["r2"]["tx"]["datagrams"] == tx["r2"].datagrams
    assert report["window"]["duration_s"] >= RUN_S
    assert report["captures"]["air"]["role"] == "medium"
    assert report["captures"]["r3"]["tcpdump"]["dropped"] == 0
    for name in report["plots"].values():
        assert (run / name).stat().st_size > 5000


def test_capture_is_listening_when_start_returns(
    fleet_factory: FleetFactory, tmp_path: Path
) -> None:
    overflows = neigh_overflows()
    lab = fleet_factory(2, start=False)
    send = (
        "import socket; s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); "
        f"s.sendto(b'NOTIFY * HTTP/1.1\\r\\n\\r\\n', ('{lab.robot('r2').ip}', 1900))"
    )
    for k in range(3):  # no sleep between start, send and stop: nothing may be lost
        path = tmp_path / f"r2-{k}.pcap"
        with Capture(ns(lab, 2), "eth0", path, bpf="udp port 1900") as cap:
            res = lab.exec("r1", [sys.executable, "-c", send])
            assert res.returncode == 0, res.stderr
        assert cap.stats is not None
        assert cap.stats.captured == 1, f"{cap.stats}{environment(overflows)}"
        (rec,) = pcap.read_pcap(path)
        assert (rec.direction, rec.src, rec.msg_type) == ("rx", lab.robot("r1").ip, "Reject")


def test_capture_errors_in_namespaces(fleet_factory: FleetFactory, tmp_path: Path) -> None:
    lab = fleet_factory(1, start=False)
    with pytest.raises(CaptureError, match="no interface wlan7 in namespace"):
        Capture(ns(lab, 1), "wlan7", tmp_path / "x.pcap").start()
    with pytest.raises(CaptureError, match="namespace 'nl-nope-r9' does not exist"):
        Capture("nl-nope-r9", "eth0", tmp_path / "x.pcap").start()
    bad = Capture(ns(lab, 1), "eth0", tmp_path / "x.pcap", bpf="udp port")
    with pytest.raises(CaptureError, match="bad capture filter"):
        bad.start()
    assert bad.pid is not None and gone(bad.pid)

    # An error inside the with block: tcpdump is stopped, the error is the one raised.
    with pytest.raises(KeyError), Capture(ns(lab, 1), "eth0", tmp_path / "y.pcap") as cap:
        raise KeyError("boom")
    assert cap.pid is not None and gone(cap.pid)

    # start_all: one bad capture, none left running.
    good = Capture(ns(lab, 1), "eth0", tmp_path / "g.pcap")
    with pytest.raises(CaptureError):
        start_all([good, Capture(ns(lab, 1), "nope0", tmp_path / "b.pcap")])
    assert good.pid is None or gone(good.pid)

    # tcpdump that dies during the capture is reported at stop.
    cap = Capture(ns(lab, 1), "eth0", tmp_path / "z.pcap").start()
    assert cap.pid is not None
    os.kill(cap.pid, 9)
    with pytest.raises(CaptureError, match="failed"):
        cap.stop()
    assert gone(cap.pid)


def _json(path: Path) -> dict[str, Any]:
    import json

    obj = json.loads(path.read_text())
    assert isinstance(obj, dict)
    return obj
