"""The paper's per-robot load against one sdfrd: publishers churning, consumers polling.

Run inside a robot's namespace; prints one JSON object with every latency
sample summarised. Requests go over plain HTTP keep-alive connections (one per
thread) to the API's TCP address, exactly as a robot's programs would; a
latency is the time from sending the request to having the whole body.
"""

from __future__ import annotations

import argparse
import json
import random
import secrets
import socket
import sys
import threading
import time
from typing import Any

from sdfr.client import calls


def merge(per_thread: list[dict[str, list[float]]]) -> tuple[dict[str, list[float]], list[float]]:
    """The load's threads' samples by request kind, and their failures apart."""
    merged: dict[str, list[float]] = {"publish": [], "unpublish": [], "neighbors": []}
    errors: list[float] = []
    for out in per_thread:
        for k, v in out.items():
            (errors if k == "errors" else merged[k]).extend(v)
    return merged, errors


def summary(samples: list[float]) -> dict[str, object]:
    if not samples:
        return {"count": 0}
    s = sorted(samples)

    def pct(p: float) -> float:
        return round(s[min(len(s) - 1, int(p / 100 * len(s)))] * 1000, 3)

    return {
        "count": len(s),
        "p50_ms": pct(50),
        "p90_ms": pct(90),
        "p99_ms": pct(99),
        "max_ms": round(s[-1] * 1000, 3),
        "mean_ms": round(sum(s) / len(s) * 1000, 3),
    }


class Worker:
    """A minimal HTTP/1.1 keep-alive client, so the generator's own cost stays small."""

    def __init__(self, host: str, port: int) -> None:
        self.where = (host, port)
        self.sock = self._connect()
        self.host = f"{host}:{port}".encode()
        # One worker is one program: what it publishes is its own to unpublish.
        self.owner = secrets.token_urlsafe(24).encode()
        self.buf = b""

    def _connect(self) -> socket.socket:
        sock = socket.create_connection(self.where, timeout=10)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return sock

    def call(self, method: str, path: str, body: bytes | None = None) -> tuple[int, bytes, float]:
        try:
            return self._call(method, path, body)
        except (ConnectionError, BrokenPipeError):
            # sdfrd closes a connection idle for a while, as a server should: open another.
            self.sock.close()
            self.sock, self.buf = self._connect(), b""
            return self._call(method, path, body)

    def _call(self, method: str, path: str, body: bytes | None = None) -> tuple[int, bytes, float]:
        head = b"%s %s HTTP/1.1\r\nHost: %s\r\nX-SDFR-Owner: %s\r\n" % (
            method.encode(),
            path.encode(),
            self.host,
            self.owner,
        )
        if body is not None:
            head += b"Content-Type: application/json\r\nContent-Length: %d\r\n" % len(body)
        request = head + b"\r\n" + (body or b"")
        t0 = time.perf_counter()
        self.sock.sendall(request)
        while b"\r\n\r\n" not in self.buf:
            self._fill()
        header, _, rest = self.buf.partition(b"\r\n\r\n")
        status = int(header[9:12])
        length = 0
        for line in header.split(b"\r\n")[1:]:
            if line[:15].lower() == b"content-length:":
                length = int(line[15:])
        while len(rest) < length:
            rest += self._recv()
        data, self.buf = rest[:length], rest[length:]
        return status, data, time.perf_counter() - t0

    def _recv(self) -> bytes:
        chunk = self.sock.recv(262144)
        if not chunk:
            raise ConnectionError("sdfrd closed the connection")
        return chunk

    def _fill(self) -> None:
        self.buf += self._recv()


def publisher(
    w: Worker, i: int, args: argparse.Namespace, stop: float, out: dict[str, list[float]]
) -> None:
    rng = random.Random(i)
    publish = calls.publish_service(
        f"publisher-{i}",
        f"bench.kind{i % 7}",
        f"http://localhost:{9000 + i}/",
        {"index": i, "rate": 10 + i % 5, "frame": f"base_link_{i}"},
    )
    # Sent without an id: sdfrd chooses one, and each publish is a new registration.
    body = json.dumps({k: v for k, v in (publish.body or {}).items() if k != "id"}).encode()
    time.sleep(rng.uniform(0, args.publish_delay / args.speedup))
    while time.monotonic() < stop:
        status, data, dt = w.call(publish.method, publish.path, body)
        if status != 201:
            out["errors"].append(status)
            return
        out["publish"].append(dt)
        sid = json.loads(data)["id"]
        time.sleep(rng.uniform(0, args.unpublish_delay / args.speedup))
        unpublish = calls.unpublish(sid)
        status, _, dt = w.call(unpublish.method, unpublish.path)
        if status != 204:
            out["errors"].append(status)
            return
        out["unpublish"].append(dt)
        time.sleep(args.publish_delay / args.speedup * rng.uniform(0.5, 1.0))


def consumer(
    w: Worker, interval: float, stop: float, out: dict[str, list[float]], sizes: list[int]
) -> None:
    rng = random.Random()
    time.sleep(rng.uniform(0, interval))
    while time.monotonic() < stop:
        if interval:
            time.sleep(interval * rng.uniform(0.5, 1.5))
        status, data, dt = w.call("GET", "/neighbors")
        if status != 200:
            out["errors"].append(status)
            return
        out["neighbors"].append(dt)
        sizes.append(len(data))


ROUTES = {
    "publish": ("POST", "/services"),
    "unpublish": ("DELETE", "/services/{id}"),
    "neighbors": ("GET", "/neighbors"),
}


def server_histograms(w: Worker) -> dict[tuple[str, str], tuple[list[tuple[float, int]], float]]:
    """The daemon's own latency histogram: (method, route) -> (cumulative buckets, sum)."""
    status, text, _ = w.call("GET", "/metrics")
    if status != 200:
        return {}
    hist: dict[tuple[str, str], tuple[list[tuple[float, int]], float]] = {}
    for line in text.decode().splitlines():
        if not line.startswith("sdfr_api_request_duration_seconds_"):
            continue
        name, _, value = line.rpartition(" ")
        labels = dict(part.split("=", 1) for part in name[name.index("{") + 1 : -1].split(","))
        key = (labels["method"].strip('"'), labels["route"].strip('"'))
        buckets, total = hist.get(key, ([], 0.0))
        if name.startswith("sdfr_api_request_duration_seconds_bucket"):
            le = labels["le"].strip('"')
            buckets.append((float("inf") if le == "+Inf" else float(le), int(float(value))))
        elif name.startswith("sdfr_api_request_duration_seconds_sum"):
            total = float(value)
        hist[key] = (buckets, total)
    return hist


def server_side(before: Any, after: Any) -> dict[str, object]:
    """Bucket bounds of the p50/p99 the daemon measured itself, and its mean, per operation."""
    out: dict[str, Any] = {}
    for op, key in ROUTES.items():
        b1, s1 = after.get(key, ([], 0.0))
        b0, s0 = before.get(key, ([(le, 0) for le, _ in b1], 0.0))
        diff = [(le, n1 - n0) for (le, n1), (_, n0) in zip(b1, b0, strict=False)]
        count = diff[-1][1] if diff else 0
        if not count:
            continue

        def bound(q: float, diff: list[tuple[float, int]] = diff, count: int = count) -> float:
            return next(le for le, n in diff if n >= q * count) * 1000

        out[op] = {
            "count": count,
            "p50_le_ms": bound(0.5),
            "p99_le_ms": bound(0.99),
            "mean_ms": round((s1 - s0) / count * 1000, 3),
        }
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--api", default="127.0.0.1:8700")
    p.add_argument("--publishers", type=int, default=70)
    p.add_argument("--consumers", type=int, default=30)
    p.add_argument("--duration", type=float, default=30.0)
    p.add_argument("--publish-delay", type=float, default=10.0)
    p.add_argument("--unpublish-delay", type=float, default=5.0)
    p.add_argument("--speedup", type=float, default=1.0, help="divide the paper's delays by this")
    p.add_argument(
        "--poll-interval",
        type=float,
        default=0.0,
        help="mean pause between a consumer's requests (0: back to back, a closed loop)",
    )
    args = p.parse_args(argv)
    host, _, port = args.api.rpartition(":")
    probe = Worker(host, int(port))
    before = server_histograms(probe)
    stop = time.monotonic() + args.duration
    per_thread: list[dict[str, list[float]]] = []
    sizes: list[int] = []
    threads = []
    for i in range(args.publishers):
        out: dict[str, list[float]] = {"publish": [], "unpublish": [], "errors": []}
        per_thread.append(out)
        threads.append(
            threading.Thread(target=publisher, args=(Worker(host, int(port)), i, args, stop, out))
        )
    for _ in range(args.consumers):
        out = {"neighbors": [], "errors": []}
        per_thread.append(out)
        threads.append(
            threading.Thread(
                target=consumer,
                args=(Worker(host, int(port)), args.poll_interval, stop, out, sizes),
            )
        )
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    merged, errors = merge(per_thread)
    result: dict[str, Any] = {k: summary(v) for k, v in merged.items()}
    result["server"] = server_side(before, server_histograms(probe))
    result["errors"] = len(errors)
    result["requests_per_s"] = round(sum(len(v) for v in merged.values()) / args.duration, 1)
    result["neighbors_bytes_mean"] = int(sum(sizes) / len(sizes)) if sizes else 0
    json.dump(result, sys.stdout)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
