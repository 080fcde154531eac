"""Whatever bytes a local program sends, the API answers: a 4xx in JSON for what it cannot
read (414 for an over-long request line), never a 500, never a silent close, never a
traceback in the log. Raw bytes on a real socket, against the whole API."""

from __future__ import annotations

import asyncio
import json
import logging
import re
import socket
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sdfr.api import Runner, TCPSite, create_app
from sdfr.api.httpparse import MAX_HEAD, MAX_LINE
from sdfr.config.load import Config
from sdfr.store import Store
from tests.support.api import free_port

OWNER = "X-SDFR-Owner: fuzz-owner-token-0123456789abcdef\r\n"


class Errors(logging.Handler):
    """Log records at WARNING and above (a traceback is logged at ERROR)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


class Server:
    """The API served by its own event loop in a thread, for the whole module (hypothesis
    sends hundreds of requests; one server takes them all, as a daemon would)."""

    def __init__(self, state_dir: Path) -> None:
        self.port = free_port()
        self.errors = Errors()
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._stop: asyncio.Event | None = None
        self._thread = threading.Thread(target=self._run, args=(state_dir,), daemon=True)
        self._thread.start()
        assert self._ready.wait(10)

    def _run(self, state_dir: Path) -> None:
        asyncio.set_event_loop(self._loop)
        self._loop.run_until_complete(self._serve(state_dir))

    async def _serve(self, state_dir: Path) -> None:
        store = Store(state_dir)
        runner = Runner(create_app(Config(state_dir=state_dir, robot_id="r1"), store))
        await runner.setup()
        await TCPSite(runner, "127.0.0.1", self.port).start()
        self._stop = asyncio.Event()
        self._ready.set()
        try:
            await self._stop.wait()
        finally:
            await runner.cleanup()
            store.close()

    def close(self) -> None:
        assert self._stop is not None
        self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(10)


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    srv = Server(tmp_path_factory.mktemp("abuse"))
    for name in ("sdfr", "asyncio"):
        logging.getLogger(name).addHandler(srv.errors)
    try:
        yield srv
    finally:
        for name in ("sdfr", "asyncio"):
            logging.getLogger(name).removeHandler(srv.errors)
        srv.close()


def send(port: int, data: bytes) -> bytes:
    """Send `data`, end the sending side, read until the server closes."""
    with socket.create_connection(("127.0.0.1", port), timeout=15) as sock:
        try:
            sock.sendall(data)
            sock.shutdown(socket.SHUT_WR)
        except (BrokenPipeError, ConnectionResetError):
            pass  # it answered and closed before reading everything: what it said counts
        out = b""
        try:
            while chunk := sock.recv(65536):
                out += chunk
        except ConnectionResetError:
            pass
    return out


def answers(data: bytes) -> list[tuple[int, dict[str, str], bytes]]:
    """The answers in what the server sent (each framed by Content-Length), in order."""
    out = []
    while data:
        head, sep, rest = data.partition(b"\r\n\r\n")
        assert sep, f"a partial answer: {data[:200]!r}"
        lines = head.decode("latin-1").split("\r\n")
        assert lines[0].startswith("HTTP/1.1 "), lines[0]
        status = int(lines[0].split()[1])
        headers = {k.lower(): v.strip() for k, _, v in (ln.partition(":") for ln in lines[1:])}
        length = int(headers.get("content-length", "0"))
        out.append((status, headers, rest[:length]))
        data = rest[length:]
    return out


def one_answer(port: int, data: bytes) -> tuple[int, dict[str, str]]:
    got = answers(send(port, data))
    assert got, "closed without an answer"
    status, _, body = got[0]
    error = json.loads(body) if status >= 400 else {}
    assert status < 400 or set(error) == {"error", "field"}
    return status, error


def no_tracebacks(server: Server) -> None:
    bad = [r for r in server.errors.records if r.levelno >= logging.ERROR or r.exc_info]
    server.errors.records.clear()
    assert not bad, [r.getMessage() for r in bad]


# -- the findings ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "value", [b"\xb2", b"\xb9\xb3", b"1\xb2", b"\xd9\xa3", b"+5", b"-1", b" 5 5"]
)
def test_a_content_length_that_is_not_digits_is_a_400(server: Server, value: bytes) -> None:
    request = (
        b"POST /services HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\n"
        b"Content-Length: " + value + b"\r\n\r\n{}"
    )
    status, error = one_answer(server.port, request)
    assert status == 400 and "Content-Length" in error["error"], (status, error)
    no_tracebacks(server)


def test_a_content_length_too_long_to_be_a_number_is_a_413(server: Server) -> None:
    request = b"POST /services HTTP/1.1\r\nHost: x\r\nContent-Length: " + b"9" * 5000 + b"\r\n\r\n"
    status, error = one_answer(server.port, request)
    assert status == 413, (status, error)
    no_tracebacks(server)


@pytest.mark.parametrize("size", [b"-5", b"+5", b"0x5", b"5_0", b"", b"g", b"\xb2", b"1" * 40])
def test_a_chunk_size_that_is_not_hex_digits_is_a_400(server: Server, size: bytes) -> None:
    request = (
        b"POST /services HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\n"
        b"Transfer-Encoding: chunked\r\n" + OWNER.encode() + b"\r\n"
        + size + b"\r\n{\"name\":\"a\",\"type\":\"t\"}\r\n0\r\n\r\n"
    )  # fmt: skip
    status, error = one_answer(server.port, request)
    assert status in (400, 413) and "chunk" in error["error"], (size, status, error)
    no_tracebacks(server)


@pytest.mark.parametrize("length", [MAX_LINE + 1, 40_000, 80_000, 200_000])
def test_an_over_long_request_line_is_a_414(server: Server, length: int) -> None:
    target = b"/neighbors?q=" + b"a" * length
    request = b"GET " + target + b" HTTP/1.1\r\nHost: localhost\r\n\r\n"
    status, error = one_answer(server.port, request)
    assert status == 414 and str(MAX_LINE) in error["error"], (length, status, error)
    no_tracebacks(server)


def test_a_head_over_its_limit_is_a_431(server: Server) -> None:
    many = b"".join(b"X-H%d: %s\r\n" % (i, b"v" * 2000) for i in range(MAX_HEAD // 2000 + 2))
    status, error = one_answer(
        server.port, b"GET /neighbors HTTP/1.1\r\nHost: x\r\n" + many + b"\r\n"
    )
    assert status == 431, (status, error)
    no_tracebacks(server)


@pytest.mark.parametrize(
    "request_bytes",
    [
        b"GET /neighbors HTTP/1.1\r\nHost: x\r\n",  # the head never ends
        b"POST /services HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\n"
        b'Content-Length: 50\r\n\r\n{"name":',  # nor does the body
        b"POST /services HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\n"
        b'Transfer-Encoding: chunked\r\n\r\n5\r\n{"na',  # nor a chunk
    ],
)
def test_a_request_cut_short_is_answered(server: Server, request_bytes: bytes) -> None:
    """The client stopped sending (it may still read): it is told why, not left hanging."""
    status, error = one_answer(server.port, request_bytes)
    assert status == 400 and "ended" in error["error"], (status, error)
    no_tracebacks(server)


# -- any input ------------------------------------------------------------------------------------

BASES = [
    b"GET /neighbors HTTP/1.1\r\nHost: localhost\r\n\r\n",
    b"GET /services/abc HTTP/1.1\r\nHost: localhost\r\n\r\n",
    b"GET /events?since=0 HTTP/1.1\r\nHost: 127.0.0.1:8700\r\n\r\n",
    b"GET /neighbors/search?type=cam&attr.fps=30 HTTP/1.1\r\nHost: localhost\r\n\r\n",
    (b"POST /services HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\n"
     + OWNER.encode() + b"Content-Length: 46\r\n\r\n"
     b'{"id":"fz","name":"cam","type":"t","ttl":60.0}'),
    (b"POST /services HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\n"
     + OWNER.encode() + b"Transfer-Encoding: chunked\r\n\r\n"
     b'1a\r\n{"id":"fz2","name":"a","ty\r\nb\r\npe":"t"}   \r\n0\r\n\r\n'),
    b"DELETE /services/fz HTTP/1.1\r\nHost: localhost\r\n" + OWNER.encode() + b"\r\n",
    (b"POST /services/fz/renew HTTP/1.1\r\nHost: localhost\r\nContent-Length: 11\r\n"
     b"Content-Type: application/json\r\n" + OWNER.encode() + b"\r\n{\"ttl\": 30}"),
    (b"POST /services HTTP/1.1\r\nHost: localhost\r\nExpect: 100-continue\r\n"
     b"Content-Type: application/json\r\nContent-Length: 26\r\n\r\n"
     b'{"name":"cam","type":"t2"}'),
    b"GET /neighbors HTTP/1.0\r\n\r\nGET /self HTTP/1.1\r\nHost: localhost\r\n\r\n",
]  # fmt: skip
#: Bytes a mutation may put in: any byte, and those that matter to a parser.
TOKENS = st.sampled_from(
    [b"\r\n", b"\r", b"\n", b" ", b":", b"\x00", b"\xb2", b"-", b"0x", b"\xff", b"\t",
     b"Content-Length: 5\r\n", b"Transfer-Encoding: chunked\r\n", b"HTTP/1.1", b"%",
     b"\r\n\r\n", b"Expect: 100-continue\r\n", b"Content-Length: -1\r\n", b"9" * 30]
) | st.binary(min_size=1, max_size=8)  # fmt: skip


@st.composite
def mutated(draw: st.DrawFn) -> bytes:
    data = bytearray(draw(st.sampled_from(BASES)))
    for _ in range(draw(st.integers(1, 4))):
        at = draw(st.integers(0, len(data)))
        how = draw(st.sampled_from(["insert", "replace", "delete", "truncate"]))
        if how == "insert":
            data[at:at] = draw(TOKENS)
        elif how == "replace":
            token = draw(TOKENS)
            data[at : at + len(token)] = token
        elif how == "delete":
            del data[at : at + draw(st.integers(1, 12))]
        else:
            del data[at:]
    return bytes(data)


#: What an answer may be: 100 Continue, a success, any client error, or 505 for an HTTP
#: version other than 1.0 and 1.1 (the standard answer to it; no other 5xx).
ALLOWED = {100, 200, 201, 204, 505} | set(range(400, 500))


@settings(max_examples=400, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=mutated())
def test_any_request_gets_an_answer_and_never_a_500(server: Server, data: bytes) -> None:
    got = answers(send(server.port, data))
    if not data.strip():  # nothing was asked
        assert got == []
        return
    assert got, f"closed without an answer: {data!r}"
    for status, headers, body in got:
        assert status in ALLOWED, (status, body, data)
        if status == 505:  # only for a well-formed version that is not 1.0 or 1.1
            versions = re.findall(rb"HTTP/[0-9]\.[0-9]", data)
            assert set(versions) - {b"HTTP/1.0", b"HTTP/1.1"}, data
        if status >= 400:
            assert headers["content-type"].startswith("application/json"), data
            error = json.loads(body)
            assert set(error) == {"error", "field"} and error["error"], data
    no_tracebacks(server)
