"""The API's HTTP server: every error is JSON, also what fails before any handler runs
(a malformed request, an oversize line), and idle or half-sent connections are closed."""

from __future__ import annotations

import logging
import time
from typing import Any

from aiohttp import web
from aiohttp.http_exceptions import LineTooLong
from aiohttp.web_protocol import RequestHandler
from aiohttp.web_request import BaseRequest

from sdfr.api.replies import Handler, RequestError, cannot_write_status, error_response
from sdfr.api.state import state_of
from sdfr.errors import ValidationError
from sdfr.keystore import KeyringError
from sdfr.store import (
    StateWriteError,
)

log = logging.getLogger("sdfr.api")


#: An idle or half-sent connection is closed after this many seconds (slowloris).
IDLE_TIMEOUT = 15.0


def _http_message(exc: web.HTTPException, request: web.Request) -> str:
    if exc.status == 404:
        return f"no such endpoint: {request.path}"
    if exc.status == 405:
        allowed = exc.headers.get("Allow", "")
        return f"method {request.method} is not allowed on {request.path}; allowed: {allowed}"
    text = (exc.text or "").removeprefix(f"{exc.status}: ")
    return text or exc.reason


@web.middleware
async def errors_as_json(request: web.Request, handler: Handler) -> web.StreamResponse:
    """Every error, the router's 404/405 included, is `{"error": ..., "field": ...}`."""
    try:
        return await handler(request)
    except ValidationError as exc:
        return error_response(422, exc.message, exc.field)
    except (RequestError, KeyringError) as exc:
        return error_response(exc.status, exc.message, exc.field)
    except StateWriteError as exc:
        # Nothing was stored: say why, and let /health say it too until a write succeeds.
        state_of(request).write_problem = (time.time(), exc.reason, str(exc))
        return error_response(cannot_write_status(exc.reason), str(exc), "state_dir")
    except web.HTTPException as exc:
        if exc.status < 400:
            raise
        drop = ("content-type", "content-length")
        keep = {k: v for k, v in exc.headers.items() if k.lower() not in drop}
        return error_response(exc.status, _http_message(exc, request), None, keep)
    except Exception:
        log.exception("%s %s failed", request.method, request.path)
        return error_response(500, "internal error; the daemon's log has the details")


# -- applications ------------------------------------------------------------------------------


_PARSE_ERRORS = {
    400: "malformed HTTP request",
    413: "the request is too large",
    414: "the request line (path and query) is longer than 8190 bytes",
    431: "a request header is longer than 8190 bytes, or there are too many",
}


class _JsonErrorHandler(RequestHandler):
    """aiohttp's connection handler, answering what fails before any handler runs (a
    malformed request, an oversize line or header, a method no parser knows) in JSON like
    every other error, and logging it at debug level (a port scan must not fill the log)."""

    def handle_error(
        self,
        request: BaseRequest,
        status: int = 500,
        exc: BaseException | None = None,
        message: str | None = None,
    ) -> web.StreamResponse:
        log.debug("%s from %s: %s", status, request.remote, message or exc)
        if request.writer.output_size > 0:
            raise ConnectionError("a response was sent already; cannot send an error")
        text = _PARSE_ERRORS.get(status, "internal error; the daemon's log has the details")
        detail = (message or "").strip().splitlines()
        if isinstance(exc, LineTooLong):
            text = "the request line or a header is longer than 8190 bytes"
        elif status == 400 and detail:
            text = f"{text}: {detail[0][:120]}"
        resp = error_response(status, text)
        resp.force_close()
        return resp


class _JsonErrorServer(web.Server):
    def __call__(self) -> RequestHandler:
        return _JsonErrorHandler(self, loop=self._loop, **self._kwargs)


class Runner(web.AppRunner):
    """An AppRunner whose every answer is JSON (see _JsonErrorHandler) and which closes idle
    and half-sent connections after IDLE_TIMEOUT."""

    def __init__(self, app: web.Application, **kwargs: Any) -> None:
        kwargs.setdefault("keepalive_timeout", IDLE_TIMEOUT)
        super().__init__(app, **kwargs)

    async def _make_server(self) -> web.Server:
        server = await super()._make_server()
        server.__class__ = _JsonErrorServer  # same state; only __call__ differs
        return server
