"""Answers of the API: JSON bodies, error answers (`{"error": ..., "field": ...}`), and
reading a request's JSON body."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Awaitable, Callable, Mapping
from typing import Any

from sdfr.api.http import Request, Response

#: A registration is at most one datagram; a request body never needs more than this.
MAX_BODY = 64 * 1024


#: Longest a request body may take to arrive (a slow sender holds a connection, no more).
BODY_TIMEOUT = 10.0


#: What answers a request.
Handler = Callable[[Request], Awaitable[Response]]


class RequestError(Exception):
    """An error answer other than a validation error (422): status, message, field."""

    def __init__(
        self,
        status: int,
        message: str,
        field: str | None = None,
        headers: Mapping[str, str] | None = None,
    ) -> None:
        super().__init__(message)
        self.status = status
        self.message = message
        self.field = field
        self.headers = headers


def json_bytes(obj: Any) -> bytes:
    return json.dumps(obj, ensure_ascii=False, separators=(",", ":"), allow_nan=False).encode()


def json_response(
    body: Any, status: int = 200, headers: Mapping[str, str] | None = None
) -> Response:
    data = body if isinstance(body, bytes) else json_bytes(body)
    return Response(
        body=data, status=status, headers=headers, content_type="application/json", charset="utf-8"
    )


def error_response(
    status: int, message: str, field: str | None = None, headers: Mapping[str, str] | None = None
) -> Response:
    return json_response({"error": message, "field": field}, status, headers)


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not valid JSON")


async def read_json(request: Request) -> Any:
    try:
        raw = await asyncio.wait_for(request.read(), BODY_TIMEOUT)
    except TimeoutError:
        raise RequestError(
            408, f"the request body did not arrive within {BODY_TIMEOUT:.0f} s"
        ) from None
    if not raw.strip():
        raise RequestError(400, "the request body is empty; expected a JSON object")
    try:
        # NaN and Infinity are not JSON: accepting them would store values no client can read.
        return json.loads(raw, parse_constant=_reject_constant)
    except UnicodeDecodeError:
        raise RequestError(400, "invalid JSON: the body is not UTF-8") from None
    except ValueError as exc:
        raise RequestError(400, f"invalid JSON: {exc}") from None
    except RecursionError:
        raise RequestError(400, "invalid JSON: nested too deeply") from None


def cannot_write_status(reason: str) -> int:
    """The answer to a write the state directory refused: 507 when it is full, else 503."""
    return 507 if reason == "full" else 503
