"""One datagram of each kind: its bytes unsigned and sealed, and the CPU to seal it, to check
its seal, and to take it through the protocol core's whole receive path."""

from __future__ import annotations

import statistics
import time
from collections import Counter
from collections.abc import Callable
from functools import partial

from bench.auth.fixtures import COUNTER, KEY, SEQ, check, seal, services
from sdfr import wire
from sdfr.protocol import auth
from sdfr.protocol.auth import Keyring, Sealed
from sdfr.records.model import service_digest
from sdfr.testing.simnet import SimNet
from sdfr.wire import Alive, Byebye, Discovery, Origin, Response, Update

#: Kinds of datagram sent to one robot (sealed for it), the rest to the fleet.
UNICAST_KINDS = frozenset(
    {
        "ping (unicast Discovery)",
        "ping reply (compact Response)",
        "ping reply carrying a ping",
        "ping reply (compact form)",
    }
)


def datagram_kinds() -> dict[str, bytes]:
    """One datagram of each kind, unsigned, as robot r1 of fleet 1 sends it."""
    svcs = services("r1", 100)
    origin = Origin(1, "r1", 219_000_000, 42, service_digest(svcs))
    compact = Origin(1, "r1", 219_000_000, 42, service_digest(svcs), wire.WIRE_COMPACT)
    location = "http://10.1.0.1:8701/description.json"
    peer = ("10.1.0.2", 1900)
    parts = wire.encode_update_parts(origin, location, 30, svcs)
    delta = Update(origin, location, 30, 0, 1, (svcs[0],), base=41, removed=())
    return {
        "search (multicast Discovery)": wire.encode(
            Discovery(origin, wire.fleet_target(1), 1, want=wire.WANT_ALL)
        ),
        "ping (unicast Discovery)": wire.encode(
            Discovery(origin, "uuid:r2", 0, seq=SEQ, multicast=False),
            group=peer[0],
            port=peer[1],
        ),
        "ping reply (compact Response)": wire.encode(Response(origin, "uuid:r1", "", 0, SEQ)),
        "ping reply carrying a ping": wire.encode(Response(origin, "uuid:r1", "", 0, SEQ, SEQ + 1)),
        "ping reply (compact form)": wire.encode(
            Response(compact, "uuid:r1", "", 0, SEQ), compact=True
        ),
        "beacon (Alive)": wire.encode(Alive(origin, location, 30)),
        "beacon that pings (compact Alive)": wire.encode(
            Alive(compact, "", 0, SEQ, 1), compact=True
        ),
        "one-service delta (Update)": wire.encode(delta),
        "full Update part": max(parts, key=len),
        "Byebye": wire.encode(Byebye(origin)),
    }


def sealed_kind(kind: str, data: bytes, counter: int = COUNTER) -> bytes:
    to = "r2" if kind in UNICAST_KINDS else None
    return seal(data, counter, to=to, sender="10.1.0.1")


def bytes_per_datagram() -> dict[str, dict[str, float]]:
    out = {}
    for kind, data in datagram_kinds().items():
        sealed = sealed_kind(kind, data)
        assert len(sealed) <= wire.MAX_DATAGRAM
        out[kind] = {
            "unsigned": len(data),
            "signed": len(sealed),
            "overhead": len(sealed) - len(data),
            "overhead_pct": round(100 * (len(sealed) - len(data)) / len(data), 1),
        }
    return out


def update_parts() -> dict[str, int]:
    """How many Update parts a whole set of 100 services takes (the codec leaves
    `wire.SEAL_RESERVE` bytes of each free for a seal)."""
    svcs = services("r1", 100)
    origin = Origin(1, "r1", 219_000_000, 42, service_digest(svcs))
    parts = wire.encode_update_parts(origin, "http://10.1.0.1:8701/description.json", 30, svcs)
    return {
        "seal_reserve": wire.SEAL_RESERVE,
        "parts_for_100_services": len(parts),
        "bytes_for_100_services": sum(len(p) for p in parts),
    }


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
        to = "r2" if kind in UNICAST_KINDS else None
        sealed = sealed_kind(kind, data)
        assert isinstance(check(sealed, ring, me="r2", src="10.1.0.1"), Sealed)
        out[label] = {
            "bytes": len(data),
            "seal_us": per_call_us(
                partial(seal, data, COUNTER, to=to, sender="10.1.0.1"), n, repeats
            ),
            "check_us": per_call_us(
                partial(check, sealed, ring, me="r2", src="10.1.0.1"), n, repeats
            ),
            "check_unsigned_us": per_call_us(
                partial(check, data, ring, me="r2", src="10.1.0.1"), n, repeats
            ),
        }
    return out


def receive_cpu(n: int, repeats: int) -> dict[str, float]:
    """µs per datagram through Core.receive: beacons and pings of a peer it has proven.

    r1 and r2 meet in the simulator first (r1 challenges r2, r2 answers: r2 is listed by r1,
    by either core's rules); then r1's core alone is fed a stream of r2's beacons and pings,
    4 ms apart (under the per-source limit, and within r2's proof window)."""
    out: dict[str, float] = {}
    for label, ring in (("unsigned", auth.OPEN), ("signed", Keyring.of([KEY]))):
        samples = []
        for r in range(repeats):
            net = SimNet(seed=r + 1)
            net.add("r1", services=services("r1", 10), keyring=ring)
            net.add("r2", services=services("r2", 10), keyring=ring)
            net.run_for(15.0)
            assert net.all_see_all(["r1", "r2"]), "r1 and r2 did not meet"
            core, peer = net.nodes["r1"].core, net.nodes["r2"].core
            src = net.nodes["r2"].addr
            origin = peer._origin()
            stream = [
                (wire.encode(Alive(origin, peer.location, 30)), None),
                (
                    wire.encode(
                        Discovery(origin, "uuid:r1", 0, seq=77, multicast=False),
                        group=net.nodes["r1"].addr[0],
                        port=1900,
                    ),
                    "r1",
                ),
            ]
            first = peer._sent_seals + 1
            datagrams = [
                seal(stream[i % 2][0], first + i, to=stream[i % 2][1], sender=src[0])
                if ring.keyed
                else stream[i % 2][0]
                for i in range(n)
            ]
            core.datagrams_to_send()
            rejects = Counter(core.counters.rejects)
            t_start = net.now
            t0 = time.perf_counter()
            for i, data in enumerate(datagrams):
                core.receive(data, src, t_start + i * 4e-3)
                core.datagrams_to_send()
            samples.append((time.perf_counter() - t0) / n * 1e6)
            assert core.counters.rejects == rejects, core.counters.rejects - rejects
            assert "r2" in core.reachable()
        out[f"{label}_us"] = round(statistics.median(samples), 3)
    out["overhead_us"] = round(out["signed_us"] - out["unsigned_us"], 3)
    return out
