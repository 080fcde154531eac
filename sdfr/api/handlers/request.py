"""What a request carries beyond its body: its owner token and who asks, its query
parameters."""

from __future__ import annotations

import re
from collections.abc import Iterable

from sdfr.api.http import Request
from sdfr.api.replies import RequestError
from sdfr.endpoints import OWNER_HEADER
from sdfr.errors import ValidationError
from sdfr.store import Caller, hash_token

#: What an owner token is: at least 128 bits of URL-safe base64 (secrets.token_urlsafe(16)).
OWNER_TOKEN = re.compile(r"[A-Za-z0-9_-]{22,128}")


def owner_token(request: Request) -> str | None:
    """The owner token the request carries (None: none); a 400 when it is not one."""
    token = request.headers.get(OWNER_HEADER)
    if token is not None and not OWNER_TOKEN.fullmatch(token):
        raise RequestError(
            400,
            f"{OWNER_HEADER} is not an owner token: 22-128 characters of A-Z a-z 0-9 _ - (the "
            "owner_token a publish was answered with, or one the program chose, such as "
            "secrets.token_urlsafe(32))",
            OWNER_HEADER,
        )
    return token


def caller(request: Request, token: str | None) -> Caller:
    """Who asks: its token's hash, and on the unix socket its uid."""
    return Caller(None if token is None else hash_token(token), request.peer_uid)


def not_yours(service_id: str) -> RequestError:
    return RequestError(
        403,
        f"service {service_id!r} belongs to the program that published it: only its owner "
        f"may unpublish, renew, hold or publish it again. Send its owner token ({OWNER_HEADER}: "
        "the owner_token the publish was answered with), or call over the unix socket as the "
        "user that published it (or root); anyone may read it",
        OWNER_HEADER,
    )


def only_params(request: Request, allowed: Iterable[str]) -> None:
    known = set(allowed)
    for key in request.query:
        if key not in known:
            hint = ", ".join(sorted(known)) or "none"
            raise ValidationError(key, f"unknown query parameter (known: {hint})")


#: What a yes/no query parameter may be (the OpenAPI document lists these); alone it is yes.
FLAG_VALUES = {
    "1": True,
    "true": True,
    "yes": True,
    "": True,
    "0": False,
    "false": False,
    "no": False,
}


def query_flag(request: Request, name: str) -> bool:
    raw = request.query.get(name)
    if raw is None:
        return False
    if raw not in FLAG_VALUES:
        raise ValidationError(name, "must be 1/0, true/false or yes/no")
    return FLAG_VALUES[raw]
