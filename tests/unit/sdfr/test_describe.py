"""The description server the discovery layer runs for the fleet: small, JSON, bounded."""

from __future__ import annotations

import asyncio
import json
import socket
import time
from collections.abc import Callable, Coroutine
from typing import Any

from sdfr.daemon.describe import DescribeServer
from tests.support.api import aio, free_port, raw_exchange

BODY = json.dumps({"robot_id": "r1", "services": []}).encode()


async def serving(
    test: Callable[[DescribeServer, int], Coroutine[Any, Any, None]], **limits: Any
) -> None:
    server = DescribeServer(lambda: BODY, **limits)
    port = free_port()
    await server.listen("127.0.0.1", port)
    try:
        await test(server, port)
    finally:
        server.close()


@aio
async def test_the_description_and_every_error_are_json() -> None:
    async def test(server: DescribeServer, port: int) -> None:
        def get(request: bytes) -> tuple[int, dict[str, str], bytes]:
            return raw_exchange(port, request)

        for path in (b"/description.json", b"/", b"/description.json?x=1"):
            status, headers, body = await asyncio.to_thread(
                get, b"GET " + path + b" HTTP/1.1\r\n\r\n"
            )
            assert status == 200 and body == BODY and headers["connection"] == "close"
            assert headers["content-type"].startswith("application/json")
        status, headers, body = await asyncio.to_thread(get, b"HEAD / HTTP/1.0\r\n\r\n")
        assert status == 200 and body == b"" and headers["content-length"] == str(len(BODY))
        for request, code in (
            (b"POST /description.json HTTP/1.1\r\nContent-Length: 2\r\n\r\n{}", 405),
            (b"GET /services HTTP/1.1\r\n\r\n", 404),
            (b"\x16\x03\x01garbage\r\n\r\n", 400),
            (b"GET /" + b"a" * 9000 + b" HTTP/1.1\r\n\r\n", 431),
        ):
            status, headers, body = await asyncio.to_thread(get, request)
            assert status == code and set(json.loads(body)) == {"error", "field"}, request[:20]
        assert server.served == 7

    await serving(test)


@aio
async def test_connections_are_bounded_in_number_and_in_time() -> None:
    async def test(server: DescribeServer, port: int) -> None:
        def hold(n: int) -> list[socket.socket]:
            return [socket.create_connection(("127.0.0.1", port), timeout=5) for _ in range(n)]

        held = await asyncio.to_thread(hold, 3)
        await asyncio.sleep(0.1)
        assert server.status().open == 2 and server.refused == 1  # 2 per client
        t0 = time.monotonic()
        # An idle connection is dropped at the deadline, whatever it sends or not.
        await asyncio.to_thread(lambda: [s.recv(1) for s in held[:2]])
        assert 0.3 <= time.monotonic() - t0 < 2.0
        for s in held:
            s.close()
        await asyncio.sleep(0.1)
        assert server.status().open == 0

    await serving(test, per_client=2, deadline=0.5)
