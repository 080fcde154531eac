"""The API's HTTP server: every error is JSON, also what fails before any handler runs
(a malformed request, an oversize line), and idle or half-sent connections are closed."""

from __future__ import annotations

import logging
import time
from typing import Any

from sdfr.api import httpserve
from sdfr.api.http import App, Request, Response, RouteError
from sdfr.api.httpparse import HttpError
from sdfr.api.replies import Handler, RequestError, cannot_write_status, error_response
from sdfr.api.state import state_of
from sdfr.config.keystore import KeyringError
from sdfr.errors import ValidationError
from sdfr.store import (
    StateWriteError,
)

log = logging.getLogger("sdfr.api")


#: An idle or half-sent connection is closed after this many seconds (slowloris).
IDLE_TIMEOUT = 15.0


def _route_error(exc: RouteError, request: Request) -> Response:
    if exc.status == 405:
        allowed = ",".join(exc.allow)
        return error_response(
            405,
            f"method {request.method} is not allowed on {request.path}; allowed: {allowed}",
            None,
            {"Allow": allowed},
        )
    return error_response(404, f"no such endpoint: {request.path}")


async def errors_as_json(request: Request, handler: Handler) -> Response:
    """Every error, the router's 404/405 included, is `{"error": ..., "field": ...}`."""
    try:
        return await handler(request)
    except ValidationError as exc:
        return error_response(422, exc.message, exc.field)
    except (RequestError, KeyringError) as exc:
        headers = exc.headers if isinstance(exc, RequestError) else None
        return error_response(exc.status, exc.message, exc.field, headers)
    except StateWriteError as exc:
        # Nothing was stored: say why, and let /health say it too until a write succeeds.
        state_of(request).write_problem = (time.time(), exc.reason, str(exc))
        return error_response(cannot_write_status(exc.reason), str(exc), "state_dir")
    except RouteError as exc:
        return _route_error(exc, request)
    except HttpError as exc:  # the body could not be read (too large, malformed)
        resp = error_response(exc.status, exc.message)
        resp.force_close = True
        return resp
    except ConnectionError:
        raise  # the client went away: nothing to answer
    except Exception:
        log.exception("%s %s failed", request.method, request.path)
        return error_response(500, "internal error; the daemon's log has the details")


_PARSE_ERRORS = {
    400: "malformed HTTP request",
    413: "the request is too large",
    431: "the request's head is too large",
    505: "HTTP version not supported",
}


def json_parse_error(status: int, message: str) -> Response:
    """The answer to what fails before any handler runs (a malformed request, an oversize
    line or header, a method no parser knows): JSON like every other error, the request
    never echoed back."""
    text = message.strip().splitlines()[0][:160] if message.strip() else ""
    return error_response(status, text or _PARSE_ERRORS.get(status, "malformed HTTP request"))


class Runner(httpserve.Runner):
    """The API's runner: errors before any handler are JSON, and idle and half-sent
    connections are closed after IDLE_TIMEOUT."""

    def __init__(self, app: App, **kwargs: Any) -> None:
        kwargs.setdefault("keepalive_timeout", IDLE_TIMEOUT)
        kwargs.setdefault("error_answer", json_parse_error)
        super().__init__(app, **kwargs)
