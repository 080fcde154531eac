"""Reading HTTP/1.1 requests: the limits, the request head, headers, query strings and
chunked bodies; a request that breaks them is an `HttpError` (its status, and why)."""

from __future__ import annotations

import asyncio
import re
from collections.abc import Iterator, Mapping
from urllib.parse import parse_qsl

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
#: The methods HTTP parsers know (llhttp's list): one the API does not serve is a 405 naming
#: what is allowed; any other token is a malformed request (400).
KNOWN_METHODS = frozenset(
    b"DELETE GET HEAD POST PUT CONNECT OPTIONS TRACE COPY LOCK MKCOL MOVE PROPFIND PROPPATCH "
    b"SEARCH UNLOCK BIND REBIND UNBIND ACL REPORT MKACTIVITY CHECKOUT MERGE M-SEARCH NOTIFY "
    b"SUBSCRIBE UNSUBSCRIBE PATCH PURGE MKCALENDAR LINK UNLINK SOURCE QUERY".split()
)
_TOKEN = re.compile(rb"^[!#$%&'*+\-.^_`|~0-9A-Za-z]+$")


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


def content_length(headers: Headers) -> int:
    """The body's length its Content-Length header says (0 without one)."""
    if "Content-Length" not in headers:
        return 0
    value = headers["Content-Length"].strip()
    # (isascii: "²" and other digits of Unicode pass isdigit(), not int())
    if not (value.isascii() and value.isdigit()):
        raise HttpError(400, "Content-Length is not a number (digits 0-9 only)")
    if len(value) > _MAX_DIGITS:
        raise HttpError(413, f"Content-Length {value[:20]}... is over any body limit")
    return int(value)


def parse_head(head: bytes, methods: frozenset[bytes]) -> tuple[bytes, bytes, str, Headers]:
    """A request's head (up to its blank line) as (method, target, version, headers), of one
    of `methods`."""
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
    if method not in methods:
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
    return method, target, version.decode(), Headers(pairs)


async def read_chunked(reader: asyncio.StreamReader, limit: int) -> bytes:
    """A chunked body from `reader`, at most `limit` bytes (413 past it); trailers read and
    dropped."""
    out = bytearray()
    while True:
        line = await reader.readuntil(b"\r\n")
        size_text = line.split(b";", 1)[0].strip(b" \t\r\n")
        # (int(x, 16) takes "-5", "+5", "0x5" and "5_0": a size is hex digits only)
        if not _HEX_SIZE.fullmatch(size_text):
            raise HttpError(400, "malformed chunked body: a chunk size is 1-16 hex digits")
        size = int(size_text, 16)
        if size == 0:
            trailers = 0
            while (trailer := await reader.readuntil(b"\r\n")) != b"\r\n":
                trailers += len(trailer)  # trailers: ignored, but not without end
                if trailers > MAX_HEAD:
                    raise HttpError(431, f"the trailers are over {MAX_HEAD} bytes")
            return bytes(out)
        if len(out) + size > limit:
            raise HttpError(413, f"the request is too large (over {limit} bytes)")
        out += await reader.readexactly(size)
        if await reader.readexactly(2) != b"\r\n":
            raise HttpError(400, "malformed chunked body")
