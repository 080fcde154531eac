"""The local API's HTTP/1.1 server, on asyncio streams: requests, answers, streamed answers
(Server-Sent Events), routes, middlewares, and the listeners (TCP, unix socket).

The daemon's only HTTP server. It does what a REST API for programs on this robot needs and
no more: HTTP/1.1 keep-alive and pipelining, bodies by Content-Length or chunked, `Expect:
100-continue`, chunked streamed answers, bounded lines, headers, bodies and waits, and an
answer in JSON to what it cannot read (the API's `errors_as_json` does the same for what a
handler refuses). aiohttp's server did the same for about 18 MiB a process; this costs about
0.3 MiB. Clients are unaffected: it is the same HTTP.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
import socket
import struct
import time
from collections.abc import Awaitable, Callable, Iterator, Mapping
from typing import Any, Generic, TypeVar, cast
from urllib.parse import parse_qsl, unquote

log = logging.getLogger("sdfr.api")

#: Longest request line or header line (bytes), as aiohttp's and most servers' limit.
MAX_LINE = 8190
#: Most header lines one request may have.
MAX_HEADERS = 100
#: Most bytes a request's head (request line and headers) may have.
MAX_HEAD = 64 * 1024
#: Longest Content-Length (digits) and chunk size (hex digits) read as a number: anything
#: longer is far over any body limit, and Python's int() refuses over 4,300 digits.
_MAX_DIGITS = 18
_HEX_SIZE = re.compile(rb"[0-9A-Fa-f]{1,16}")
_VERSION = re.compile(rb"HTTP/[0-9]\.[0-9]")
#: After an error answer the connection closes; what the client is still sending is read
#: (up to this many bytes and seconds) first, so that the close does not reset the
#: connection and destroy the answer before the client has read it.
LINGER_BYTES = 1 << 20
LINGER_SECONDS = 2.0
REASONS = {
    100: "Continue", 200: "OK", 201: "Created", 204: "No Content", 400: "Bad Request",
    401: "Unauthorized", 403: "Forbidden", 404: "Not Found", 405: "Method Not Allowed",
    408: "Request Timeout", 409: "Conflict", 411: "Length Required", 413:
    "Payload Too Large", 414: "URI Too Long", 415: "Unsupported Media Type", 422:
    "Unprocessable Content", 429: "Too Many Requests", 431: "Request Header Fields Too Large",
    500: "Internal Server Error", 503: "Service Unavailable", 505:
    "HTTP Version Not Supported", 507: "Insufficient Storage",
}  # fmt: skip
#: The methods HTTP parsers know (llhttp's list): one the API does not serve is a 405 naming
#: what is allowed; any other token is a malformed request (400).
KNOWN_METHODS = frozenset(
    b"DELETE GET HEAD POST PUT CONNECT OPTIONS TRACE COPY LOCK MKCOL MOVE PROPFIND PROPPATCH "
    b"SEARCH UNLOCK BIND REBIND UNBIND ACL REPORT MKACTIVITY CHECKOUT MERGE M-SEARCH NOTIFY "
    b"SUBSCRIBE UNSUBSCRIBE PATCH PURGE MKCALENDAR LINK UNLINK SOURCE QUERY".split()
)
_TOKEN = re.compile(rb"^[!#$%&'*+\-.^_`|~0-9A-Za-z]+$")

T = TypeVar("T")


class HttpError(Exception):
    """A request that cannot be read (the connection closes after the answer)."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status
        self.message = message


class Headers(Mapping[str, str]):
    """A request's headers, by case-insensitive name; repeated ones joined with ", "."""

    def __init__(self, pairs: list[tuple[str, str]]) -> None:
        self._d: dict[str, str] = {}
        for name, value in pairs:
            key = name.lower()
            self._d[key] = f"{self._d[key]}, {value}" if key in self._d else value

    def __getitem__(self, name: str) -> str:
        return self._d[name.lower()]

    def __contains__(self, name: object) -> bool:
        return isinstance(name, str) and name.lower() in self._d

    def __iter__(self) -> Iterator[str]:
        return iter(self._d)

    def __len__(self) -> int:
        return len(self._d)


class Query:
    """A query string's parameters, in order, repeats kept (`?event=a&event=b`)."""

    def __init__(self, raw: str) -> None:
        self._pairs = parse_qsl(raw, keep_blank_values=True)

    def get(self, name: str, default: str | None = None) -> str | None:
        for key, value in self._pairs:
            if key == name:
                return value
        return default

    def getall(self, name: str, default: list[str] | None = None) -> list[str]:
        found = [value for key, value in self._pairs if key == name]
        return found if found or default is None else default

    def items(self) -> list[tuple[str, str]]:
        return list(self._pairs)

    def __iter__(self) -> Iterator[str]:
        return (key for key, _ in self._pairs)

    def __contains__(self, name: object) -> bool:
        return any(key == name for key, _ in self._pairs)

    def __len__(self) -> int:
        return len(self._pairs)


class AppKey(Generic[T]):
    """A typed key of what an App holds for its handlers."""

    def __init__(self, name: str, kind: type[T]) -> None:
        self.name = name
        self.kind = kind

    def __repr__(self) -> str:
        return f"AppKey({self.name!r})"


class Response:
    """A whole answer."""

    def __init__(
        self,
        body: bytes = b"",
        status: int = 200,
        headers: Mapping[str, str] | None = None,
        content_type: str | None = None,
        charset: str | None = None,
    ) -> None:
        self.body = body
        self.status = status
        self.headers: dict[str, str] = dict(headers or {})
        if content_type is not None:
            ctype = content_type if charset is None else f"{content_type}; charset={charset}"
            self.headers["Content-Type"] = ctype
        self.prepared = False
        self.force_close = False

    def head(self, version: str, close: bool, length: int | None) -> bytes:
        lines = [f"{version} {self.status} {REASONS.get(self.status, 'Unknown')}"]
        lines += [f"{k}: {v}" for k, v in self.headers.items() if k.lower() != "content-length"]
        if length is not None and self.status != 204 and self.status >= 200:
            lines.append(f"Content-Length: {length}")
        if close:
            lines.append("Connection: close")
        return ("\r\n".join(lines) + "\r\n\r\n").encode("latin-1")


class StreamResponse(Response):
    """An answer written as it goes (Server-Sent Events, a held lease): `prepare`, then
    `write` as often as needed, then `write_eof`. Chunked on HTTP/1.1; on HTTP/1.0 the end of
    the connection ends it. The connection closes after it, so what the client sends
    meanwhile is only watched for its end: `gone` is set when the client goes away (a handler
    waiting between writes can stop at once), and a write after that raises ConnectionError."""

    def __init__(self, status: int = 200, headers: Mapping[str, str] | None = None) -> None:
        super().__init__(b"", status, headers)
        self._conn: _Connection | None = None
        self._chunked = True
        self._eof = False
        self.gone = asyncio.Event()
        self._watch: asyncio.Task[None] | None = None

    async def prepare(self, request: Request) -> None:
        conn = request._conn
        self._conn = conn
        self._chunked = request.version == "HTTP/1.1"
        if self._chunked:
            self.headers["Transfer-Encoding"] = "chunked"
        conn.keep_alive = False
        self.prepared = True
        await request.read()  # (what is left of a body, so that only its end is watched)
        self._watch = asyncio.get_running_loop().create_task(self._watch_end(conn))
        await conn.send(self.head("HTTP/1.1", True, None))

    async def _watch_end(self, conn: _Connection) -> None:
        with contextlib.suppress(Exception):
            while await conn.reader.read(4096):
                pass
        self.gone.set()
        conn.gone = True

    async def write(self, data: bytes) -> None:
        if self._conn is None or self._eof:
            raise RuntimeError("write before prepare, or after write_eof")
        if not data:
            return
        if self._chunked:
            data = b"%x\r\n%s\r\n" % (len(data), data)
        await self._conn.send(data)

    async def write_eof(self) -> None:
        if self._conn is None or self._eof:
            return
        self._eof = True
        if self._watch is not None:
            self._watch.cancel()
        if self._chunked:
            await self._conn.send(b"0\r\n\r\n")


class Request:
    """One request: what it asks for, and its body on demand (`read`)."""

    def __init__(
        self,
        conn: _Connection,
        app: App,
        method: str,
        target: str,
        version: str,
        headers: Headers,
    ) -> None:
        self._conn = conn
        self.app = app
        self.method = method
        self.version = version
        self.headers = headers
        raw_path, _, raw_query = target.partition("?")
        self.raw_path = raw_path
        self.path = unquote(raw_path)
        self.query = Query(raw_query)
        self.match_info: dict[str, str] = {}
        #: The route's pattern, as `/services/{id}` (None: no route matched).
        self.route: str | None = None
        self.remote = conn.remote
        self.over_unix = conn.unix
        self._body: bytes | None = None
        self._length = 0
        self._chunked = False
        te = headers.get("Transfer-Encoding", "").lower()
        if te:
            if te != "chunked":
                raise HttpError(400, f"unsupported Transfer-Encoding {te[:40]!r}")
            self._chunked = True
        elif "Content-Length" in headers:
            value = headers["Content-Length"].strip()
            # (isascii: "²" and other digits of Unicode pass isdigit(), not int())
            if not (value.isascii() and value.isdigit()):
                raise HttpError(400, "Content-Length is not a number (digits 0-9 only)")
            if len(value) > _MAX_DIGITS:
                raise HttpError(413, f"Content-Length {value[:20]}... is over any body limit")
            self._length = int(value)

    @property
    def body_exists(self) -> bool:
        return self._chunked or self._length > 0

    @property
    def content_type(self) -> str:
        """The body's media type, lower case, without parameters (as aiohttp says it:
        application/octet-stream when the header is missing)."""
        value = self.headers.get("Content-Type", "")
        media = value.split(";", 1)[0].strip().lower()
        return media or "application/octet-stream"

    async def read(self) -> bytes:
        """The body (at most the connection's max_body: 413 past it)."""
        if self._body is None:
            self._body = await self._conn.read_body(self)
        return self._body

    @property
    def peer_uid(self) -> int | None:
        """The uid of the program at the other end of a unix socket (SO_PEERCRED, as the
        kernel saw it connect); None over TCP."""
        return self._conn.peer_uid()

    @property
    def addresses(self) -> tuple[tuple[str, int], tuple[str, int]] | None:
        """(this end, the client's end) of a TCP connection: (address, port) each; None on
        a unix socket."""
        return self._conn.addresses()


Handler = Callable[[Request], Awaitable[Response]]
Middleware = Callable[[Request, Handler], Awaitable[Response]]


class RouteError(Exception):
    """No route for a request: 404 (no such path) or 405 (not with this method: `allow`)."""

    def __init__(self, status: int, allow: tuple[str, ...] = ()) -> None:
        super().__init__(status)
        self.status = status
        self.allow = allow


_PARAM = re.compile(r"\{(\w+)(?::([^{}]*(?:\{[^{}]*\}[^{}]*)*))?\}")


def _compile(path: str) -> tuple[re.Pattern[str], str]:
    """A route's pattern (`/services/{id}`, `{id:REGEX}`) as a regex, and its canonical form."""
    out, pos = [], 0
    for m in _PARAM.finditer(path):
        out.append(re.escape(path[pos : m.start()]))
        out.append(f"(?P<{m.group(1)}>{m.group(2) or '[^{}/]+'})")
        pos = m.end()
    out.append(re.escape(path[pos:]))
    return re.compile("".join(out) + r"\Z"), _PARAM.sub(lambda m: "{" + m.group(1) + "}", path)


class App:
    """Routes, middlewares (outermost first), what the handlers share (`app[KEY]`), and
    what runs when the server starts, stops taking requests, and is done."""

    def __init__(self, middlewares: list[Middleware] | None = None, max_body: int = 1 << 20):
        self.middlewares = list(middlewares or [])
        self.max_body = max_body
        self._routes: list[tuple[str, re.Pattern[str], str, Handler]] = []
        self._state: dict[AppKey[Any], Any] = {}
        self.on_startup: list[Callable[[App], Awaitable[None]]] = []
        self.on_shutdown: list[Callable[[App], Awaitable[None]]] = []
        self.on_cleanup: list[Callable[[App], Awaitable[None]]] = []

    def __getitem__(self, key: AppKey[T]) -> T:
        return cast(T, self._state[key])

    def __setitem__(self, key: AppKey[T], value: T) -> None:
        self._state[key] = value

    def routes(self) -> list[tuple[str, str]]:
        """(method, canonical path) of every route, as added."""
        return [(method, canonical) for method, _, canonical, _ in self._routes]

    def add_route(self, method: str, path: str, handler: Handler) -> None:
        regex, canonical = _compile(path)
        self._routes.append((method, regex, canonical, handler))

    def resolve(self, request: Request) -> Handler:
        """The handler of `request` (its match_info and route set), else RouteError."""
        allow: list[str] = []
        for method, regex, canonical, handler in self._routes:
            m = regex.match(request.path)
            if m is None:
                continue
            if method != request.method:
                allow.append(method)
                continue
            request.match_info = m.groupdict()
            request.route = canonical
            return handler
        if allow:
            raise RouteError(405, tuple(dict.fromkeys(allow)))
        raise RouteError(404)

    async def handle(self, request: Request) -> Response:
        """Through the middlewares to the route's handler (a RouteError is raised inside the
        chain, so that the middlewares answer it as they answer a handler's error)."""

        async def route(req: Request) -> Response:
            return await self.resolve(req)(req)

        call: Handler = route
        for mw in reversed(self.middlewares):
            call = _bind(mw, call)
        return await call(request)


def _bind(mw: Middleware, inner: Handler) -> Handler:
    async def call(request: Request) -> Response:
        return await mw(request, inner)

    return call


#: What answers a request the server could not read: (status, message) -> the answer.
ErrorAnswer = Callable[[int, str], Response]


def plain_error(status: int, message: str) -> Response:
    return Response(message.encode(), status, content_type="text/plain", charset="utf-8")


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
        lines = head[:-4].split(b"\r\n")
        while lines and not lines[0]:  # (empty lines before a request are allowed)
            lines.pop(0)
        if not lines:
            raise HttpError(400, "malformed HTTP request: empty")
        if len(lines[0]) > MAX_LINE:
            raise HttpError(414, f"the request line is longer than {MAX_LINE} bytes")
        parts = lines[0].split(b" ")
        if len(parts) != 3 or not parts[2].startswith(b"HTTP/"):
            raise HttpError(400, "malformed HTTP request: not a request line")
        method, target, version = parts
        if not _TOKEN.match(method):
            raise HttpError(400, "malformed HTTP request: a method is a token")
        if method not in self.runner.methods:
            raise HttpError(400, f"unknown method {method[:20].decode('latin-1')!r}")
        if version not in (b"HTTP/1.1", b"HTTP/1.0"):
            if not _VERSION.fullmatch(version):
                raise HttpError(400, "malformed HTTP request: not an HTTP version")
            raise HttpError(505, f"HTTP version {version.decode()} not supported")
        if not target.startswith(b"/"):
            raise HttpError(400, "malformed HTTP request: the target is not a path")
        if len(lines) - 1 > MAX_HEADERS:
            raise HttpError(400, f"too many headers (more than {MAX_HEADERS})")
        pairs = []
        for line in lines[1:]:
            if len(line) > MAX_LINE:
                raise HttpError(400, f"a header is longer than {MAX_LINE} bytes")
            name, colon, value = line.partition(b":")
            if not colon or not _TOKEN.match(name):
                raise HttpError(400, "malformed HTTP request: a header line is not NAME: VALUE")
            pairs.append((name.decode("latin-1"), value.strip().decode("latin-1")))
        headers = Headers(pairs)
        v = version.decode()
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
            out = bytearray()
            while True:
                line = await self.reader.readuntil(b"\r\n")
                size_text = line.split(b";", 1)[0].strip(b" \t\r\n")
                # (int(x, 16) takes "-5", "+5", "0x5" and "5_0": a size is hex digits only)
                if not _HEX_SIZE.fullmatch(size_text):
                    raise HttpError(400, "malformed chunked body: a chunk size is 1-16 hex digits")
                size = int(size_text, 16)
                if size == 0:
                    trailers = 0
                    while (trailer := await self.reader.readuntil(b"\r\n")) != b"\r\n":
                        trailers += len(trailer)  # trailers: ignored, but not without end
                        if trailers > MAX_HEAD:
                            raise HttpError(431, f"the trailers are over {MAX_HEAD} bytes")
                    return bytes(out)
                if len(out) + size > limit:
                    raise HttpError(413, f"the request is too large (over {limit} bytes)")
                out += await self.reader.readexactly(size)
                if await self.reader.readexactly(2) != b"\r\n":
                    raise HttpError(400, "malformed chunked body")
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
