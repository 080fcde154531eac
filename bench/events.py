"""What GET /events costs: appending to the event log, its size on disk, the latency from a
change to a subscriber (a publish in the API layer; a robot change committed by another
process, as the discovery layer does, woken by its datagram), and the API layer's CPU with
idle streams open. A real API layer process on a temporary state directory, loopback only;
about 30 s. JSON on stdout and in runs/bench-events.json."""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from sdfr.client import Client
from sdfr.daemon.channel import EVENTS, STATUS_SOCKET
from sdfr.records.events import Event, Tracker
from sdfr.records.model import PeerRecord, Service
from sdfr.store import EVENT_LOG_MAX, Store

OUT = Path("runs/bench-events.json")


def peer(i: int, services: int = 3) -> PeerRecord:
    return PeerRecord(
        robot_id=f"r{i}", address=f"10.3.0.{i % 250}", location="http://x/", boot_id=1,
        version=1, digest="d" * 16, reachable=True, first_seen=0.0, last_seen=0.0,
        indicator=1.0, rtt_ms=1.0, pings=20,
        services=tuple(Service(f"s{i}-{k}", f"cam {k}", "camera/rgb", None, {"fps": 30})
                       for k in range(services)),
    )  # fmt: skip


def append_cost(tmp: Path) -> dict[str, Any]:
    """µs per history save with and without an event (the discovery layer's hot path)."""
    store = Store(tmp / "append")
    records = [peer(i) for i in range(20)]
    n = 2000
    t0 = time.perf_counter()
    for k in range(n):
        store.save_history((), [records[k % 20]])
    plain = (time.perf_counter() - t0) / n
    t0 = time.perf_counter()
    for k in range(n):
        store.save_history((), [records[k % 20]], [Event("robot.indicator", "r1", {"x": k})])
    with_event = (time.perf_counter() - t0) / n
    tracker = Tracker((0.5, 0.8))
    t0 = time.perf_counter()
    for k in range(n):
        tracker.observe(records[k % 20])
    diff = (time.perf_counter() - t0) / n
    # The log full: EVENT_LOG_MAX typical events (an appeared robot with 3 services).
    appeared = Tracker().observe(peer(1))[0]
    store.save_history((), [], [appeared] * EVENT_LOG_MAX)
    store._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    size = sum(p.stat().st_size for p in (tmp / "append").glob("state.db*"))
    store.close()
    return {
        "history_save_us": round(plain * 1e6, 1),
        "history_save_with_event_us": round(with_event * 1e6, 1),
        "tracker_observe_us": round(diff * 1e6, 2),
        "typical_event_bytes": len(appeared.body(1, 0.0)),
        "log_max_events": EVENT_LOG_MAX,
        "state_db_bytes_with_full_log": size,
    }


def _stat_cpu(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _rss(pid: int) -> int:
    return int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def latency(tmp: Path, subscribers: int, changes: int = 100) -> dict[str, Any]:
    """Change -> every subscriber, through a real API layer process."""
    state = tmp / f"lat{subscribers}"
    state.mkdir()
    sock = state / "api.sock"
    proc = subprocess.Popen(
        [sys.executable, "-m", "sdfr.daemon.apiserver", "--state-dir", str(state), "--api",
         "127.0.0.1:0", "--describe", "127.0.0.1:0", "--robot-id", "b1", "--iface", "lo",
         "--log-level", "warning"],
    )  # fmt: skip
    try:
        with Client(unix_socket=sock, timeout=2.0) as c:
            deadline = time.monotonic() + 20
            while True:
                try:
                    c.health()
                    break
                except Exception:
                    if time.monotonic() > deadline:
                        raise
                    time.sleep(0.05)
            start = c.events(since=None)["last_id"]
        arrivals: dict[int, list[float]] = {}
        lock = threading.Lock()
        ready = threading.Barrier(subscribers + 1)

        def subscribe() -> None:
            with Client(unix_socket=sock) as w:
                stream = w.watch(since=start)
                ready.wait()
                for change in stream:
                    service = change.data.get("service") or {}
                    mark = change.data.get("mark", service.get("attributes", {}).get("mark"))
                    if isinstance(mark, int):
                        with lock:
                            arrivals.setdefault(mark, []).append(time.perf_counter())
                    if mark == 2 * changes - 1:
                        return

        threads = [threading.Thread(target=subscribe, daemon=True) for _ in range(subscribers)]
        for t in threads:
            t.start()
        ready.wait()
        time.sleep(0.5)  # every stream is open
        sent: dict[int, float] = {}
        writer = Store(state)  # the discovery layer's side: another process's connection
        wake = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        cpu0, t_idle0 = _stat_cpu(proc.pid), time.monotonic()
        with Client(unix_socket=sock) as c:
            for k in range(changes):  # API-side changes: a publish each
                sent[k] = time.perf_counter()
                c.publish("cam", "camera/rgb", attributes={"mark": k})
                time.sleep(0.01)
        for k in range(changes, 2 * changes):  # discovery-side changes
            sent[k] = time.perf_counter()
            writer.save_history((), [], [Event("robot.appeared", "r9", {"mark": k})])
            wake.sendto(EVENTS, str(state / STATUS_SOCKET))
            time.sleep(0.01)
        for t in threads:
            t.join(30)
        busy_cpu = _stat_cpu(proc.pid) - cpu0
        busy_s = time.monotonic() - t_idle0
        writer.close()
        cpu1 = _stat_cpu(proc.pid)
        time.sleep(5.0)
        idle_cpu = (_stat_cpu(proc.pid) - cpu1) / 5.0
        rss = _rss(proc.pid)

        def summary(keys: range) -> dict[str, float]:
            lat = sorted((a - sent[k]) * 1000 for k in keys for a in arrivals.get(k, []))
            if not lat:
                return {"count": 0}
            return {
                "count": len(lat),
                "p50_ms": round(statistics.median(lat), 2),
                "p99_ms": round(lat[min(len(lat) - 1, int(0.99 * len(lat)))], 2),
                "max_ms": round(lat[-1], 2),
            }

        return {
            "subscribers": subscribers,
            "publish_to_subscriber": summary(range(changes)),
            "discovery_commit_to_subscriber": summary(range(changes, 2 * changes)),
            "api_cpu_share_while_streaming": round(busy_cpu / busy_s, 3),
            "api_cpu_share_idle_streams_open": round(idle_cpu, 5),
            "api_rss_bytes": rss,
        }
    finally:
        proc.terminate()
        proc.wait(10)


def main(argv: list[str] | None = None) -> None:
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args(argv)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        result = {"append": append_cost(tmp), "latency": [latency(tmp, n) for n in (1, 16, 64)]}
    text = json.dumps(result, indent=2)
    OUT.parent.mkdir(exist_ok=True)
    OUT.write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
