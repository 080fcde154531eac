"""The API's HTTP/1.1 server (sdfr.api.http) on its own: keep-alive and pipelining, bodies
by Content-Length and chunked, Expect: 100-continue, streamed answers, HTTP/1.0, limits, and
what it says about requests it cannot read. Real sockets, raw bytes."""

from __future__ import annotations

import asyncio
import socket

from sdfr.api.http import App, AppKey, Request, Response, StreamResponse
from sdfr.api.httpserve import Runner, TCPSite
from tests.support.api import aio, free_port

GONE = AppKey("gone", asyncio.Event)


async def echo(request: Request) -> Response:
    body = await request.read()
    text = f"{request.method} {request.path} {request.query.getall('q', [])} {len(body)}:"
    return Response(text.encode() + body, content_type="text/plain")


async def stream(request: Request) -> Response:
    resp = StreamResponse(headers={"Content-Type": "text/event-stream"})
    await resp.prepare(request)
    for i in range(3):
        await resp.write(f"data: {i}\n\n".encode())
    await resp.write_eof()
    return resp


async def wait_gone(request: Request) -> Response:
    resp = StreamResponse()
    await resp.prepare(request)
    await resp.write(b"started\n")
    await asyncio.wait_for(resp.gone.wait(), 5)
    request.app[GONE].set()
    return resp


async def served() -> tuple[Runner, int]:
    app = App(max_body=1000)
    app.add_route("POST", "/echo", echo)
    app.add_route("GET", "/echo", echo)
    app.add_route("GET", "/stream", stream)
    app.add_route("GET", "/gone", wait_gone)
    app[GONE] = asyncio.Event()
    runner = Runner(app, keepalive_timeout=2.0)
    await runner.setup()
    port = free_port()
    await TCPSite(runner, "127.0.0.1", port).start()
    return runner, port


def exchange(port: int, data: bytes, *, half_close: bool = True) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
        sock.sendall(data)
        if half_close:
            sock.shutdown(socket.SHUT_WR)
        out = b""
        while chunk := sock.recv(65536):
            out += chunk
    return out


@aio
async def test_pipelined_requests_are_answered_in_order() -> None:
    runner, port = await served()
    try:
        data = (
            b"POST /echo?q=1&q=2 HTTP/1.1\r\nHost: x\r\nContent-Length: 5\r\n\r\nhello"
            b"GET /echo HTTP/1.1\r\nHost: x\r\n\r\n"
            b"GET /nope HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n"
        )
        out = await asyncio.to_thread(exchange, port, data)
    finally:
        await runner.cleanup()
    answers = out.split(b"HTTP/1.1 ")[1:]
    assert [a[:3] for a in answers] == [b"200", b"200", b"404"]
    assert answers[0].endswith(b"POST /echo ['1', '2'] 5:hello")
    assert answers[1].endswith(b"GET /echo [] 0:")
    assert b"Connection: close" in answers[2]


@aio
async def test_a_chunked_body_and_expect_100_continue() -> None:
    runner, port = await served()
    try:
        chunked = (
            b"POST /echo HTTP/1.1\r\nHost: x\r\nTransfer-Encoding: chunked\r\n\r\n"
            b"3\r\nabc\r\n4;ext=1\r\ndefg\r\n0\r\nX-Trailer: 1\r\n\r\n"
        )
        out = await asyncio.to_thread(exchange, port, chunked)
        assert out.startswith(b"HTTP/1.1 200") and out.endswith(b"7:abcdefg")

        def expect() -> bytes:
            with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
                sock.sendall(
                    b"POST /echo HTTP/1.1\r\nHost: x\r\nContent-Length: 3\r\n"
                    b"Expect: 100-continue\r\nConnection: close\r\n\r\n"
                )
                first = sock.recv(100)
                sock.sendall(b"xyz")
                rest = b""
                while chunk := sock.recv(65536):
                    rest += chunk
                return first + rest

        out = await asyncio.to_thread(expect)
        assert out.startswith(b"HTTP/1.1 100 Continue\r\n\r\nHTTP/1.1 200")
        assert out.endswith(b"3:xyz")
    finally:
        await runner.cleanup()


@aio
async def test_limits_and_unreadable_requests() -> None:
    runner, port = await served()
    try:
        too_big = b"POST /echo HTTP/1.1\r\nHost: x\r\nContent-Length: 1001\r\n\r\n" + b"a" * 1001
        out = await asyncio.to_thread(exchange, port, too_big)
        assert out.startswith(b"HTTP/1.1 413") and b"Connection: close" in out
        cases = {
            b"BREW /echo HTTP/1.1\r\n\r\n": b"400",  # not a method any parser knows
            b"TRACE /echo HTTP/1.1\r\n\r\n": b"405",  # a known one the route lacks
            b"GET /echo HTTP/2.0\r\n\r\n": b"505",
            b"GET echo HTTP/1.1\r\n\r\n": b"400",
            b"GET /echo HTTP/1.1\r\nNo colon here\r\n\r\n": b"400",
            b"GET /echo HTTP/1.1\r\nContent-Length: x\r\n\r\n": b"400",
            b"GET /echo HTTP/1.1\r\nTransfer-Encoding: gzip\r\n\r\n": b"400",
        }
        for request, status in cases.items():
            out = await asyncio.to_thread(exchange, port, request)
            assert out[9:12] == status, (request, out[:60])
        out = await asyncio.to_thread(exchange, port, b"TRACE /echo HTTP/1.1\r\n\r\n")
        assert b"Allow: POST,GET" in out
    finally:
        await runner.cleanup()


@aio
async def test_streams_are_chunked_and_http10_closes() -> None:
    runner, port = await served()
    try:
        out = await asyncio.to_thread(exchange, port, b"GET /stream HTTP/1.1\r\nHost: x\r\n\r\n")
        head, _, body = out.partition(b"\r\n\r\n")
        assert b"Transfer-Encoding: chunked" in head
        assert body == b"9\r\ndata: 0\n\n\r\n9\r\ndata: 1\n\n\r\n9\r\ndata: 2\n\n\r\n0\r\n\r\n"
        out = await asyncio.to_thread(exchange, port, b"GET /stream HTTP/1.0\r\n\r\n")
        head, _, body = out.partition(b"\r\n\r\n")
        assert b"chunked" not in head and body == b"data: 0\n\ndata: 1\n\ndata: 2\n\n"
        out = await asyncio.to_thread(
            exchange, port, b"GET /echo HTTP/1.0\r\n\r\n", half_close=False
        )
        assert out.startswith(b"HTTP/1.1 200") and b"Connection: close" in out
    finally:
        await runner.cleanup()


@aio
async def test_a_stream_sees_its_client_go_away() -> None:
    runner, port = await served()
    try:

        def start_and_leave() -> bytes:
            with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
                sock.sendall(b"GET /gone HTTP/1.1\r\nHost: x\r\n\r\n")
                seen = b""
                while b"started" not in seen and (chunk := sock.recv(1000)):
                    seen += chunk
                return seen

        first = await asyncio.to_thread(start_and_leave)
        assert b"started" in first
        await asyncio.wait_for(runner.app[GONE].wait(), 5)
    finally:
        await runner.cleanup()


@aio
async def test_an_idle_connection_is_closed() -> None:
    runner, port = await served()
    try:

        def idle() -> bytes:
            with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
                return sock.recv(100)  # nothing sent: closed after keepalive_timeout (2 s)

        assert await asyncio.wait_for(asyncio.to_thread(idle), 8) == b""
    finally:
        await runner.cleanup()
