"""The API's HTTP/1.1 connection loop and listeners: each connection's requests read,
answered in order, and closed when they must be (`Runner`, `TCPSite`, `UnixSite`)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import struct
import time
from collections.abc import Awaitable, Callable

from sdfr.api.http import (
    REASONS,
    App,
    ErrorAnswer,
    Request,
    Response,
    RouteError,
    StreamResponse,
    plain_error,
)
from sdfr.api.httpparse import (
    KNOWN_METHODS,
    MAX_HEAD,
    MAX_LINE,
    HttpError,
    parse_head,
    read_chunked,
)

log = logging.getLogger("sdfr.api")
#: After an error answer the connection closes; what the client is still sending is read
#: (up to this many bytes and seconds) first, so that the close does not reset the
#: connection and destroy the answer before the client has read it.
LINGER_BYTES = 1 << 20
LINGER_SECONDS = 2.0


class _Connection:
    """One client connection: requests read, answered, in order."""

    def __init__(
        self,
        runner: Runner,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        unix: bool,
    ) -> None:
        self.runner = runner
        self.reader = reader
        self.writer = writer
        self.unix = unix
        peer = writer.get_extra_info("peername")
        self.remote = peer[0] if isinstance(peer, tuple) else "unix"
        self.keep_alive = True
        self.busy = False
        #: The client closed its side (seen while a stream was being written).
        self.gone = False
        #: An error answer ended it: what the client still sends is read before closing.
        self.linger = False
        self._uid: int | None = None

    def peer_uid(self) -> int | None:
        if not self.unix:
            return None
        if self._uid is None:
            sock = self.writer.get_extra_info("socket")
            cred = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
            self._uid = struct.unpack("3i", cred)[1]
        return self._uid

    def addresses(self) -> tuple[tuple[str, int], tuple[str, int]] | None:
        if self.unix:
            return None
        here = self.writer.get_extra_info("sockname")
        there = self.writer.get_extra_info("peername")
        if not isinstance(here, tuple) or not isinstance(there, tuple):
            return None
        return (here[0], here[1]), (there[0], there[1])

    async def send(self, data: bytes) -> None:
        if self.gone or self.writer.is_closing():
            raise ConnectionResetError("the client closed the connection")
        self.writer.write(data)
        await self.writer.drain()

    async def serve(self) -> None:
        runner = self.runner
        try:
            while self.keep_alive and not runner.closing:
                try:
                    head = await asyncio.wait_for(self._read_head(), runner.keepalive_timeout)
                except (asyncio.TimeoutError, ConnectionError, asyncio.IncompleteReadError):
                    return  # idle, half-sent, or gone
                except HttpError as exc:  # a head that cannot be read: say why, then close
                    await self._refuse(exc)
                    return
                if head is None:
                    return
                self.busy = True
                try:
                    await self._one(head)
                finally:
                    self.busy = False
        except ConnectionError:
            pass
        except Exception:  # a bug: logged, and the connection closed (never the server)
            log.exception("connection from %s failed", self.remote)
        finally:
            if self.linger and not runner.closing:
                await self._linger()
            with contextlib.suppress(Exception):
                self.writer.close()

    async def _read_head(self) -> bytes | None:
        try:
            head = await self.reader.readuntil(b"\r\n\r\n")
            while not head.strip(b"\r\n"):  # empty lines between requests: no request
                head = await self.reader.readuntil(b"\r\n\r\n")
        except asyncio.IncompleteReadError as exc:
            if exc.partial.strip():
                raise HttpError(400, "the request ended before its headers did") from None
            return None
        except asyncio.LimitOverrunError:
            # No end of the head within MAX_HEAD: is it the request line that has no end?
            start = (await self.reader.read(MAX_LINE + 4)).lstrip(b"\r\n")
            if start and b"\n" not in start:
                raise HttpError(414, f"the request line is longer than {MAX_LINE} bytes") from None
            raise HttpError(431, f"the request's head is longer than {MAX_HEAD} bytes") from None
        return head

    async def _refuse(self, exc: HttpError) -> None:
        """Answer what could not be read as a request, and end the connection."""
        log.debug("%s from %s: %s", exc.status, self.remote, exc.message)
        self.keep_alive = False
        self.linger = True
        await self.send(self._answer(self.runner.error_answer(exc.status, exc.message), None))

    async def _linger(self) -> None:
        """Stop sending, then read (and drop) what the client still sends, up to LINGER_BYTES
        and LINGER_SECONDS: closing with unread data would reset the connection, and the
        client could lose the answer it was sent."""
        loop = asyncio.get_running_loop()
        end = loop.time() + LINGER_SECONDS
        left = LINGER_BYTES
        with contextlib.suppress(Exception):
            if self.writer.can_write_eof():
                self.writer.write_eof()
            while left > 0 and (wait := end - loop.time()) > 0:
                data = await asyncio.wait_for(self.reader.read(65536), wait)
                if not data:
                    return
                left -= len(data)

    def _parse(self, head: bytes) -> Request:
        method, target, v, headers = parse_head(head, self.runner.methods)
        conn = headers.get("Connection", "").lower()
        self.keep_alive = "keep-alive" in conn if v == "HTTP/1.0" else "close" not in conn
        try:
            return Request(self, self.runner.app, method.decode(), target.decode(), v, headers)
        except UnicodeDecodeError:
            raise HttpError(400, "malformed HTTP request: the target is not ASCII") from None

    async def _one(self, head: bytes) -> None:
        runner = self.runner
        started = time.perf_counter()
        try:
            request = self._parse(head)
        except HttpError as exc:
            await self._refuse(exc)
            return
        except Exception:  # (a bug of the parser: still an answer, not a closed connection)
            log.exception("a request from %s could not be parsed", self.remote)
            await self._refuse(HttpError(400, "malformed HTTP request"))
            return
        try:
            response = await runner.app.handle(request)
        except HttpError as exc:  # the body could not be read
            self.keep_alive = False
            self.linger = True
            response = runner.error_answer(exc.status, exc.message)
        except RouteError as exc:  # (no middleware answered it)
            response = runner.error_answer(exc.status, REASONS[exc.status])
            if exc.allow:
                response.headers["Allow"] = ",".join(exc.allow)
        except ConnectionError:
            raise
        except Exception:
            log.exception("%s %s failed", request.method, request.path)
            if request._body is None and request.body_exists:
                self.keep_alive = False
            response = runner.error_answer(500, "internal error")
        if response.force_close:
            self.keep_alive = False
            self.linger = True
        if not response.prepared:
            if not await self._skip_body(request):
                self.keep_alive = False
            await self.send(self._answer(response, request))
        elif isinstance(response, StreamResponse):
            await response.write_eof()
            if not await self._skip_body(request):
                self.keep_alive = False
        if runner.access_log is not None:
            runner.access_log.info(
                '%s "%s %s" %d %.1f ms',
                self.remote,
                request.method,
                request.raw_path,
                response.status,
                1000 * (time.perf_counter() - started),
            )

    def _answer(self, response: Response, request: Request | None) -> bytes:
        body = b"" if response.status in (204, 304) else response.body
        return response.head("HTTP/1.1", not self.keep_alive, len(body)) + body

    async def _skip_body(self, request: Request) -> bool:
        """Read what the handler left of the body, so the next request starts where it
        should; False when the connection must close instead."""
        if request._body is not None or not request.body_exists:
            return True
        if request.headers.get("Expect", "").lower() == "100-continue":
            return False  # it never sent the body: closing is simplest
        try:
            await asyncio.wait_for(request.read(), self.runner.body_timeout)
        except (HttpError, asyncio.TimeoutError, asyncio.IncompleteReadError):
            return False
        return True

    async def read_body(self, request: Request) -> bytes:
        limit = self.runner.app.max_body
        if request.headers.get("Expect", "").lower() == "100-continue":
            if request._length > limit:
                raise HttpError(413, f"the request is too large (over {limit} bytes)")
            await self.send(b"HTTP/1.1 100 Continue\r\n\r\n")
        try:
            if not request._chunked:
                if request._length > limit:
                    raise HttpError(413, f"the request is too large (over {limit} bytes)")
                return await self.reader.readexactly(request._length)
            return await read_chunked(self.reader, limit)
        except asyncio.LimitOverrunError:
            raise HttpError(400, "malformed chunked body: a line without end") from None
        except asyncio.IncompleteReadError:
            # The client stopped sending (it may still be reading): tell it.
            raise HttpError(400, "the request ended before its body did") from None


class Runner:
    """Serves an App on listeners (`TCPSite`, `UnixSite`) until `cleanup`."""

    def __init__(
        self,
        app: App,
        *,
        keepalive_timeout: float = 15.0,
        body_timeout: float = 10.0,
        shutdown_timeout: float = 5.0,
        access_log: logging.Logger | None = None,
        error_answer: ErrorAnswer = plain_error,
    ) -> None:
        self.app = app
        self.keepalive_timeout = keepalive_timeout
        self.body_timeout = body_timeout
        self.shutdown_timeout = shutdown_timeout
        self.access_log = access_log
        self.error_answer = error_answer
        self.closing = False
        self.methods = KNOWN_METHODS
        self._servers: list[asyncio.AbstractServer] = []
        self._tasks: dict[asyncio.Task[None], _Connection] = {}

    async def setup(self) -> None:
        for hook in self.app.on_startup:
            await hook(self.app)

    def _client(
        self, unix: bool
    ) -> Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]:
        async def client(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            conn = _Connection(self, reader, writer, unix)
            task = asyncio.current_task()
            assert task is not None
            self._tasks[task] = conn
            try:
                await conn.serve()
            except asyncio.CancelledError:
                if not self.closing:
                    raise
                # Stopping: end quietly (asyncio's streams of Python 3.11 log a cancelled
                # connection handler as an unhandled exception).
            finally:
                self._tasks.pop(task, None)

        return client

    async def _listening(self, server: asyncio.AbstractServer) -> None:
        self._servers.append(server)

    async def cleanup(self) -> None:
        """Stop listening, end streams (on_shutdown), let requests in flight finish (up to
        shutdown_timeout), close every connection, then on_cleanup."""
        self.closing = True
        for server in self._servers:
            server.close()
        for hook in self.app.on_shutdown:
            await hook(self.app)
        deadline = time.monotonic() + self.shutdown_timeout
        for task, conn in list(self._tasks.items()):
            if not conn.busy:
                task.cancel()
        while any(conn.busy for conn in self._tasks.values()) and time.monotonic() < deadline:
            await asyncio.sleep(0.02)
        tasks = list(self._tasks)
        for task in tasks:
            task.cancel()
        if tasks:
            await asyncio.gather(*tasks, return_exceptions=True)
        for server in self._servers:
            with contextlib.suppress(Exception):
                await server.wait_closed()
        self._servers.clear()
        for hook in self.app.on_cleanup:
            await hook(self.app)


class TCPSite:
    def __init__(self, runner: Runner, host: str, port: int) -> None:
        self.runner, self.host, self.port = runner, host, port

    async def start(self) -> None:
        server = await asyncio.start_server(
            self.runner._client(unix=False),
            self.host,
            self.port,
            reuse_address=True,
            limit=MAX_HEAD,
        )
        await self.runner._listening(server)


class UnixSite:
    """A listener on a unix socket: bound at `path`, or `sock`, bound already."""

    def __init__(self, runner: Runner, path: str, sock: socket.socket | None = None) -> None:
        self.runner, self.path, self.sock = runner, path, sock

    async def start(self) -> None:
        client = self.runner._client(unix=True)
        if self.sock is not None:
            server = await asyncio.start_unix_server(client, sock=self.sock, limit=MAX_HEAD)
        else:
            server = await asyncio.start_unix_server(client, self.path, limit=MAX_HEAD)
        await self.runner._listening(server)
