"""What authenticated datagrams cost: bytes per datagram and CPU per datagram, signed vs not.

Three measures, each signed and unsigned side by side in the same run:

1. bytes: every kind of datagram a robot sends (search, ping, compact reply, beacon, a
   one-service delta, a full Update part, Byebye), encoded as the daemon encodes them, then
   sealed with a counter of the size a robot reaches in a day (6 digits);
2. CPU: microseconds per datagram to seal and to check a seal (sdfr.auth), and for the whole
   receive path of the protocol core (seal check, decode, freshness, bookkeeping) fed a
   stream of a known peer's beacons and pings; medians of repeated timed loops;
3. a fleet: 6 robots with 100 services each, 5 minutes of virtual time at the product's 10 s
   beacon (the protocol core on an in-memory medium, tests/support/simnet.py), bytes each robot
   sent and received (UDP payload), open and keyed.

JSON on stdout and in --out (runs/bench-auth.json); a table on stderr.
"""

from __future__ import annotations

import argparse
import json
import platform
import random
import statistics
import sys
import time
from collections.abc import Callable
from datetime import datetime
from functools import partial
from pathlib import Path
from typing import Any

from sdfr import auth, wire
from sdfr.auth import Keyring
from sdfr.model import Service, service_digest
from sdfr.protocol import Core, CoreConfig
from sdfr.wire import Alive, Byebye, Discovery, Origin, Response, Update

ROOT = Path(__file__).resolve().parent.parent
KEY = bytes(range(32))
COUNTER = 123_456  # six digits: a robot's counter after about a day of a small fleet
FIVE_MINUTES_S = 300.0
STARTUP_S = 30.0


def services(robot: str, n: int) -> list[Service]:
    return [
        Service(
            id=f"{robot}-{i:03d}",
            name=f"{robot} service {i}",
            type=f"sensor.kind{i % 7}",
            url=f"http://{robot}.local:9000/s{i}",
            attributes={"fps": 30, "frame": f"{robot}/base_link"},
        )
        for i in range(n)
    ]


def datagram_kinds() -> dict[str, bytes]:
    """One datagram of each kind, unsigned, as robot r1 of fleet 1 sends it."""
    svcs = services("r1", 100)
    origin = Origin(1, "r1", 219_000_000, 42, service_digest(svcs))
    location = "http://10.1.0.1:8701/description.json"
    peer = ("10.1.0.2", 1900)
    parts = wire.encode_update_parts(origin, location, 30, svcs)
    delta = Update(origin, location, 30, 0, 1, (svcs[0],), base=41, removed=())
    return {
        "search (multicast Discovery)": wire.encode(
            Discovery(origin, wire.fleet_target(1), 1, want=wire.WANT_ALL)
        ),
        "ping (unicast Discovery)": wire.encode(
            Discovery(origin, "uuid:r2", 0, seq=1_234_567_890, multicast=False),
            group=peer[0],
            port=peer[1],
        ),
        "ping reply (compact Response)": wire.encode(
            Response(origin, "uuid:r1", "", 0, 1_234_567_890)
        ),
        "ping reply carrying a ping": wire.encode(
            Response(origin, "uuid:r1", "", 0, 1_234_567_890, 1_234_567_891)
        ),
        "beacon (Alive)": wire.encode(Alive(origin, location, 30)),
        "one-service delta (Update)": wire.encode(delta),
        "full Update part": max(parts, key=len),
        "Byebye": wire.encode(Byebye(origin)),
    }


def bytes_per_datagram() -> dict[str, dict[str, float]]:
    out = {}
    for kind, data in datagram_kinds().items():
        sealed = auth.seal(data, KEY, COUNTER)
        assert len(sealed) <= wire.MAX_DATAGRAM
        out[kind] = {
            "unsigned": len(data),
            "signed": len(sealed),
            "overhead": len(sealed) - len(data),
            "overhead_pct": round(100 * (len(sealed) - len(data)) / len(data), 1),
        }
    return out


def per_call_us(fn: Callable[[], object], n: int, repeats: int) -> float:
    """Median over `repeats` timed loops of `n` calls, in microseconds per call."""
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        samples.append((time.perf_counter() - t0) / n * 1e6)
    return round(statistics.median(samples), 3)


def seal_and_check_cpu(n: int, repeats: int) -> dict[str, dict[str, float]]:
    kinds = datagram_kinds()
    ring = Keyring.of([KEY])
    out = {}
    for label, kind in (
        ("ping (small)", "ping (unicast Discovery)"),
        ("full Update part", "full Update part"),
    ):
        data = kinds[kind]
        sealed = auth.seal(data, KEY, COUNTER)
        out[label] = {
            "bytes": len(data),
            "seal_us": per_call_us(partial(auth.seal, data, KEY, COUNTER), n, repeats),
            "check_us": per_call_us(partial(auth.check, sealed, ring), n, repeats),
            "check_unsigned_us": per_call_us(partial(auth.check, data, ring), n, repeats),
        }
    return out


def receive_cpu(n: int, repeats: int) -> dict[str, float]:
    """µs per datagram through Core.receive: a known, proven peer's beacons and pings."""
    peer_svcs = services("r2", 10)
    origin = Origin(1, "r2", 219_000_001, 5, service_digest(peer_svcs))
    stream = [
        wire.encode(Alive(origin, "http://10.1.0.2:8701/description.json", 30)),
        wire.encode(
            Discovery(origin, "uuid:r1", 0, seq=77, multicast=False), group="10.1.0.1", port=1900
        ),
    ]
    src = ("10.1.0.2", 1900)
    out: dict[str, float] = {}
    for label, ring in (("unsigned", auth.OPEN), ("signed", Keyring.of([KEY]))):
        samples = []
        for _ in range(repeats):
            core = Core(
                CoreConfig(fleet=1, robot_id="r1"),
                boot_id=1,
                rng=random.Random(1),
                location="http://10.1.0.1:8701/description.json",
                keyring=ring,
            )
            datagrams = [
                auth.seal(stream[i % 2], KEY, i + 1) if ring.keyed else stream[i % 2]
                for i in range(n)
            ]
            core.start(0.0)
            core.receive(datagrams[0], src, 0.0)
            core.peers["r2"].proven = True  # steady state: a peer that answered long ago
            core._answered[src] = 0.0
            core.datagrams_to_send()
            t0 = time.perf_counter()
            for i, data in enumerate(datagrams[1:], 1):
                core.receive(data, src, i * 5e-3)  # 200/s: under the per-source limit
                core.datagrams_to_send()
            samples.append((time.perf_counter() - t0) / (n - 1) * 1e6)
            assert not core.counters.rejects, core.counters.rejects
        out[f"{label}_us"] = round(statistics.median(samples), 3)
    out["overhead_us"] = round(out["signed_us"] - out["unsigned_us"], 3)
    return out


def fleet_bytes(robots: int, n_services: int, seconds: float) -> dict[str, object]:
    """Per robot, bytes sent and received, open and keyed: during the start-up (the first
    STARTUP_S, everyone fetching everyone's set), then in `seconds` of steady state scaled to
    5 minutes.  Virtual time, so the numbers are exact and the run takes a second."""
    sys.path.insert(0, str(ROOT))
    from tests.support.simnet import SimNet  # the tests' in-memory medium: one definition of it

    out: dict[str, Any] = {}
    for label, ring in (("open", auth.OPEN), ("keyed", Keyring.of([KEY]))):
        net = SimNet(seed=7)
        names = [f"r{i}" for i in range(1, robots + 1)]
        for name in names:
            net.add(name, services=services(name, n_services), keyring=ring)
        net.run_for(STARTUP_S)
        assert net.all_see_all(names)
        cores = [net.nodes[n].core for n in names]
        start = [(c.counters.bytes_out, c.counters.bytes_in) for c in cores]
        net.run_for(seconds)
        assert net.all_see_all(names)
        scale = FIVE_MINUTES_S / seconds
        out[label] = {
            "startup_tx_kb_per_robot": round(statistics.mean(s[0] for s in start) / 1000, 1),
            "startup_rx_kb_per_robot": round(statistics.mean(s[1] for s in start) / 1000, 1),
            "tx_kb_per_robot_5min": round(
                statistics.mean(
                    (c.counters.bytes_out - s[0]) * scale / 1000
                    for c, s in zip(cores, start, strict=True)
                ),
                1,
            ),
            "rx_kb_per_robot_5min": round(
                statistics.mean(
                    (c.counters.bytes_in - s[1]) * scale / 1000
                    for c, s in zip(cores, start, strict=True)
                ),
                1,
            ),
        }
    open_, keyed = out["open"], out["keyed"]
    for key in ("tx_kb_per_robot_5min", "rx_kb_per_robot_5min"):
        out[key.split("_")[0] + "_overhead_pct"] = round(100 * (keyed[key] / open_[key] - 1), 1)
    out["conditions"] = (
        f"{robots} robots, {n_services} services each, no churn, the 10 s beacon; steady state "
        f"over {seconds:.0f} s of virtual time after a {STARTUP_S:.0f} s start-up, scaled to 5 "
        "minutes (protocol core on an in-memory medium, no loss); UDP payload"
    )
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench.auth", description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "bench-auth.json")
    p.add_argument("--quick", action="store_true", help="fewer iterations (CI smoke run)")
    args = p.parse_args(argv)
    n, repeats = (2_000, 3) if args.quick else (20_000, 7)
    started = datetime.now().isoformat(timespec="seconds")
    result: dict[str, Any] = {
        "bench": "auth",
        "started": started,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "bytes_per_datagram": bytes_per_datagram(),
        "cpu_per_datagram": seal_and_check_cpu(n, repeats),
        "receive_path": receive_cpu(n // 4, repeats),
        "fleet": fleet_bytes(6, 100, 60.0 if args.quick else FIVE_MINUTES_S),
    }
    text = json.dumps(result, indent=2)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text + "\n")
    print(text)
    err = sys.stderr
    print(f"\n{'datagram':32} {'unsigned':>9} {'signed':>7} {'+bytes':>7} {'+%':>6}", file=err)
    for kind, row in result["bytes_per_datagram"].items():
        print(
            f"{kind:32} {row['unsigned']:9.0f} {row['signed']:7.0f} {row['overhead']:7.0f} "
            f"{row['overhead_pct']:6.1f}",
            file=err,
        )
    print("\nCPU, µs per datagram (median):", file=err)
    for label, row in result["cpu_per_datagram"].items():
        print(
            f"  {label:18} seal {row['seal_us']:6.2f}  check {row['check_us']:6.2f}  "
            f"check of an unsigned one {row['check_unsigned_us']:5.2f}",
            file=err,
        )
    rp = result["receive_path"]
    print(
        f"  whole receive path: unsigned {rp['unsigned_us']:.1f}, signed {rp['signed_us']:.1f} "
        f"(+{rp['overhead_us']:.1f})",
        file=err,
    )
    fl = result["fleet"]
    print(f"\nFleet ({fl['conditions']}):", file=err)
    for label in ("open", "keyed"):
        row = fl[label]
        print(
            f"  {label:5} TX {row['tx_kb_per_robot_5min']:7.1f} kB  "
            f"RX {row['rx_kb_per_robot_5min']:7.1f} kB per robot per 5 min "
            f"(start-up: TX {row['startup_tx_kb_per_robot']:.1f}, "
            f"RX {row['startup_rx_kb_per_robot']:.1f} kB)",
            file=err,
        )
    print(
        f"  keyed: TX {fl['tx_overhead_pct']:+.1f} %, RX {fl['rx_overhead_pct']:+.1f} %", file=err
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
