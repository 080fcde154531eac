"""Who may knock: the local API answers programs on this robot, not web pages (Origin,
Sec-Fetch-Site) nor names it does not own (Host: DNS rebinding); other machines only with
the token of api_token_file, when api_allow_remote lets them in at all. And who a client
is (its user), for what one client may hold."""

from __future__ import annotations

import hmac
import ipaddress
import socket
import struct
from pathlib import Path

from sdfr.api.http import Request, Response
from sdfr.api.replies import Handler, RequestError
from sdfr.api.state import state_of
from sdfr.config.load import Config
from sdfr.errors import ConfigError

#: Methods whose body, when there is one, must be JSON.
_BODY_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
#: Names the local API always answers to.
_LOCAL_HOSTS = frozenset({"127.0.0.1", "localhost", "::1"})


# -- who may knock -----------------------------------------------------------------------------


def over_unix_socket(request: Request) -> bool:
    return request.over_unix


def is_loopback(address: str) -> bool:
    """Whether a client's address is this machine's loopback (IPv4-mapped IPv6 included)."""
    try:
        ip = ipaddress.ip_address(address)
    except ValueError:
        return False
    mapped = getattr(ip, "ipv4_mapped", None)
    return bool(ip.is_loopback or (mapped is not None and mapped.is_loopback))


#: The shortest token api_token_file may hold.
API_TOKEN_MIN = 16


def load_api_token(path: Path) -> bytes:
    """The token other machines must send (api_token_file); ConfigError naming the file."""
    try:
        text = path.read_text().strip()
    except (OSError, UnicodeDecodeError) as exc:
        reason = getattr(exc, "strerror", None) or str(exc)
        raise ConfigError(f"api_token_file: cannot read {path}: {reason}") from None
    if len(text) < API_TOKEN_MIN or not text.isascii() or any(c.isspace() for c in text):
        raise ConfigError(
            f"api_token_file: {path} must hold one token of at least {API_TOKEN_MIN} characters, "
            f"without spaces (e.g. `head -c 24 /dev/urandom | base64 > {path}`)"
        )
    return text.encode()


def _bearer_ok(request: Request, token: bytes | None) -> bool:
    scheme, _, given = request.headers.get("Authorization", "").partition(" ")
    return (
        token is not None
        and scheme.lower() == "bearer"
        and hmac.compare_digest(given.strip().encode("latin-1", "replace"), token)
    )


# -- who a client is ---------------------------------------------------------------------------


def _proc_net_address(address: str, port: int) -> str:
    """(address, port) as /proc/net/tcp{,6} writes it: the address's 32-bit words in host
    byte order, in hex, then the port."""
    if ":" in address:
        raw = socket.inet_pton(socket.AF_INET6, address)
        words = struct.unpack("=4I", raw)
        return "".join(f"{w:08X}" for w in words) + f":{port:04X}"
    (word,) = struct.unpack("=I", socket.inet_aton(address))
    return f"{word:08X}:{port:04X}"


def tcp_peer_uid(here: tuple[str, int], there: tuple[str, int]) -> int | None:
    """The uid owning the client's socket of a TCP connection within this machine: the row
    of /proc/net/tcp (or tcp6) whose local end is the client's and remote end ours. None
    when there is none (no procfs; a client on another machine)."""
    table = "/proc/net/tcp6" if ":" in there[0] else "/proc/net/tcp"
    try:
        local = _proc_net_address(*there)
        remote = _proc_net_address(*here)
        with open(table) as f:
            next(f, None)
            for line in f:
                fields = line.split()
                if len(fields) > 7 and fields[1] == local and fields[2] == remote:
                    return int(fields[7])
    except (OSError, ValueError):
        return None
    return None


def client_identity(request: Request) -> tuple[str, int | None]:
    """Who a client is, for what one client may hold: `uid N` (the unix socket's peer, or
    the owner of a loopback TCP client's socket), else its address; and the uid (None: not
    known)."""
    if request.over_unix:
        uid = request.peer_uid
        return f"uid {uid}", uid
    ends = request.addresses
    uid = tcp_peer_uid(*ends) if ends is not None and is_loopback(ends[1][0]) else None
    if uid is not None:
        return f"uid {uid}", uid
    return f"address {request.remote}", None


def host_name(header: str) -> str:
    """The name or address in a Host header, without its port or brackets, lower case."""
    value = header.strip().lower()
    if value.startswith("["):
        return value[1 : value.find("]")] if "]" in value else value
    name, colon, port = value.rpartition(":")
    return name if colon and port.isdigit() and ":" not in name else value


def allowed_hosts(cfg: Config) -> frozenset[str]:
    api_host = cfg.api.rpartition(":")[0].strip("[]").lower()
    return _LOCAL_HOSTS | {api_host} | {host_name(h) for h in cfg.api_allowed_hosts}


async def doors(request: Request, handler: Handler) -> Response:
    """The write API is for programs on this robot, not for web pages they happen to show.

    - A request from another machine carries the token of api_token_file (401 without).
    - Host must be one of this API's own names (else a page on a name that resolves to
      127.0.0.1 could read the fleet: DNS rebinding); not checked on the unix socket.
    - A browser's cross-site request (Origin, Sec-Fetch-Site) is refused unless its origin
      is in api_allowed_origins; programs send neither header.
    - A body must be JSON: a form or text/plain body is what a page can send without asking.
    """
    state = state_of(request)
    tokened = False
    if not over_unix_socket(request) and not is_loopback(request.remote):
        # Another machine (only when api_allow_remote lets the API listen for it).
        if not _bearer_ok(request, state.remote_token):
            raise RequestError(
                401,
                "a request from another machine must carry Authorization: Bearer <the token "
                "in sdfrd's api_token_file>; programs on the robot need none (127.0.0.1 or "
                "the unix socket)",
                "Authorization",
                {"WWW-Authenticate": 'Bearer realm="sdfr"'},
            )
        tokened = True  # (a web page cannot know the token: no DNS rebinding to fear)
    if not over_unix_socket(request) and not tokened:
        host = request.headers.get("Host")
        if host is not None and host_name(host) not in state.hosts:
            raise RequestError(
                403,
                f"Host {host!r} is not a name of this API (allowed: "
                f"{', '.join(sorted(state.hosts))}; add more with api_allowed_hosts)",
                "Host",
            )
    origin = request.headers.get("Origin")
    site = request.headers.get("Sec-Fetch-Site")
    cross = origin is not None or (site is not None and site not in ("same-origin", "none"))
    if cross and origin not in state.cfg.api_allowed_origins:
        raise RequestError(
            403,
            f"a cross-site request from a web page ({origin or site}) is refused; a page may "
            "call the local API only from an origin in api_allowed_origins",
            "Origin",
        )
    if (
        request.method in _BODY_METHODS
        and request.body_exists
        and request.content_type != "application/json"
    ):
        raise RequestError(
            415,
            f"the body must be JSON (Content-Type: application/json), not "
            f"{request.headers.get('Content-Type') or 'untyped'}",
            "Content-Type",
        )
    return await handler(request)
