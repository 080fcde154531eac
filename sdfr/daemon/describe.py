"""The read-only description server (the LOCATION robots announce), run by the discovery layer.

Other robots and SSDP control points fetch it, so it faces the fleet: it lives with the layer
that faces the fleet, apart from the local API, whose file descriptors a flood of connections
to it can therefore never take. It is small on purpose and bounded everywhere: one request per
connection (then close), at most MAX_CONNECTIONS open and PER_CLIENT from one address, a
connection lives DEADLINE seconds at most, a request is at most MAX_REQUEST bytes. Answers are
JSON, errors included, like the local API's.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections import Counter
from collections.abc import Callable

from sdfr.records.status import Describe

log = logging.getLogger("sdfrd.describe")

MAX_CONNECTIONS = 64
PER_CLIENT = 4
DEADLINE = 5.0
MAX_REQUEST = 8192
PATHS = frozenset({"/", "/description.json"})
_REASONS = {200: "OK", 400: "Bad Request", 404: "Not Found", 405: "Method Not Allowed",
            431: "Request Header Fields Too Large"}  # fmt: skip


def _error(message: str) -> bytes:
    return json.dumps({"error": message, "field": None}).encode()


def response(status: int, body: bytes, *, head: bool = False) -> bytes:
    lines = [
        f"HTTP/1.1 {status} {_REASONS[status]}",
        "Content-Type: application/json; charset=utf-8",
        f"Content-Length: {len(body)}",
        "Cache-Control: no-cache",
        "Connection: close",
    ]
    if status == 405:
        lines.append("Allow: GET, HEAD")
    return ("\r\n".join(lines) + "\r\n\r\n").encode() + (b"" if head else body)


def answer(request: bytes, body: Callable[[], bytes]) -> bytes:
    """The whole answer to one request (its bytes up to the blank line)."""
    line = request.split(b"\n", 1)[0].strip().decode("latin-1")
    parts = line.split(" ")
    if len(parts) != 3 or not parts[2].startswith("HTTP/1."):
        return response(400, _error("malformed HTTP request"))
    method, target, _ = parts
    path = target.split("?", 1)[0]
    if path not in PATHS:
        return response(404, _error(f"no such document: {path[:100]} (try /description.json)"))
    if method not in ("GET", "HEAD"):
        return response(405, _error(f"method {method[:20]} is not allowed; allowed: GET, HEAD"))
    return response(200, body(), head=method == "HEAD")


class DescribeServer:
    """Serves `body()` at / and /description.json on one address at a time."""

    def __init__(
        self,
        body: Callable[[], bytes],
        *,
        max_connections: int = MAX_CONNECTIONS,
        per_client: int = PER_CLIENT,
        deadline: float = DEADLINE,
    ) -> None:
        self.body = body
        self.max_connections = max_connections
        self.per_client = per_client
        self.deadline = deadline
        self.where: tuple[str, int] | None = None
        self.open: Counter[str] = Counter()
        self.refused = 0
        self.served = 0
        self._server: asyncio.Server | None = None

    async def listen(self, host: str, port: int) -> None:
        """Serve on (host, port), and no longer where it served before."""
        if self.where == (host, port) and self._server is not None:
            return
        self.close()
        loop = asyncio.get_running_loop()
        self._server = await loop.create_server(
            lambda: _Connection(self), host, port, reuse_address=True, backlog=self.max_connections
        )
        self.where = (host, port)
        log.info("serving the description on http://%s:%d/description.json", host, port)

    def close(self) -> None:
        if self._server is not None:
            self._server.close()
            self._server = None
            self.where = None

    def status(self) -> Describe:
        where = None if self.where is None else f"{self.where[0]}:{self.where[1]}"
        return Describe(where, sum(self.open.values()), self.served, self.refused)


class _Connection(asyncio.Protocol):
    def __init__(self, server: DescribeServer) -> None:
        self.server = server
        self.transport: asyncio.Transport | None = None
        self.peer = ""
        self.buf = b""
        self.timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        peer = transport.get_extra_info("peername")
        self.peer = peer[0] if isinstance(peer, tuple) else "?"
        server, open_ = self.server, self.server.open
        if sum(open_.values()) >= server.max_connections or open_[self.peer] >= server.per_client:
            self.server.refused += 1
            log.debug("description: refused a connection from %s (limits)", self.peer)
            transport.abort()
            return
        self.transport = transport
        open_[self.peer] += 1
        self.timer = asyncio.get_running_loop().call_later(server.deadline, transport.abort)

    def data_received(self, data: bytes) -> None:
        if self.transport is None or self.transport.is_closing():
            return
        self.buf += data
        end = self.buf.find(b"\r\n\r\n")
        if end < 0:
            end = self.buf.find(b"\n\n")
        if end < 0 and len(self.buf) <= MAX_REQUEST:
            return  # more to come (within the deadline)
        if end < 0 or end > MAX_REQUEST:
            out = response(431, _error(f"the request is longer than {MAX_REQUEST} bytes"))
        else:
            out = answer(self.buf[:end], self.server.body)
            self.server.served += 1
        self.transport.write(out)
        self.transport.close()

    def connection_lost(self, exc: Exception | None) -> None:
        if self.timer is not None:
            self.timer.cancel()
        if self.transport is not None:
            self.server.open[self.peer] -= 1
            if self.server.open[self.peer] <= 0:
                del self.server.open[self.peer]
