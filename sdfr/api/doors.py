"""Who may knock: the local API answers programs on this robot, not web pages (Origin,
Sec-Fetch-Site) nor names it does not own (Host: DNS rebinding)."""

from __future__ import annotations

from sdfr.api.http import Request, Response
from sdfr.api.replies import Handler, RequestError
from sdfr.api.state import state_of
from sdfr.config import Config

#: Methods whose body, when there is one, must be JSON.
_BODY_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
#: Names the local API always answers to.
_LOCAL_HOSTS = frozenset({"127.0.0.1", "localhost", "::1"})


# -- who may knock -----------------------------------------------------------------------------


def over_unix_socket(request: Request) -> bool:
    return request.over_unix


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

    - Host must be one of this API's own names (else a page on a name that resolves to
      127.0.0.1 could read the fleet: DNS rebinding); not checked on the unix socket.
    - A browser's cross-site request (Origin, Sec-Fetch-Site) is refused unless its origin
      is in api_allowed_origins; programs send neither header.
    - A body must be JSON: a form or text/plain body is what a page can send without asking.
    """
    state = state_of(request)
    if not over_unix_socket(request):
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
