"""The local API's HTTP/1.1 server: requests, answers, streamed answers (Server-Sent Events),
routes and middlewares. The connection loop and the listeners are in `httpserve`, the
reading of requests and its limits in `httpparse`.

The daemon's only HTTP server. It does what a REST API for programs on this robot needs and
no more: HTTP/1.1 keep-alive and pipelining, bodies by Content-Length or chunked, `Expect:
100-continue`, chunked streamed answers, bounded lines, headers, bodies and waits, and an
answer in JSON to what it cannot read (the API's `errors_as_json` does the same for what a
handler refuses). A general server (aiohttp's) would cost far more memory in every process
(docs/architecture.md); clients see the same HTTP.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
from collections.abc import Awaitable, Callable, Mapping
from typing import Any, Generic, Protocol, TypeVar, cast
from urllib.parse import unquote

from sdfr.api.httpparse import Headers, HttpError, Query, content_length

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

T = TypeVar("T")


class Connection(Protocol):
    """What a request and a streamed answer use of the connection they came on
    (`httpserve`'s)."""

    reader: asyncio.StreamReader
    remote: str
    unix: bool
    keep_alive: bool
    gone: bool

    async def send(self, data: bytes) -> None: ...

    async def read_body(self, request: Request) -> bytes: ...

    def peer_uid(self) -> int | None: ...

    def addresses(self) -> tuple[tuple[str, int], tuple[str, int]] | None: ...


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
        self._conn: Connection | None = None
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

    async def _watch_end(self, conn: Connection) -> None:
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
        conn: Connection,
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
        else:
            self._length = content_length(headers)

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
