"""The fleet as discovery found it: neighbours, searches, every robot known."""

from __future__ import annotations

from sdfr.api.handlers.request import only_params, query_flag
from sdfr.api.http import Request, Response
from sdfr.api.replies import json_response
from sdfr.api.state import neighbor_json, state_of
from sdfr.errors import ValidationError
from sdfr.records.model import PeerRecord


def _neighbors(peers: list[PeerRecord], include_unreachable: bool) -> dict[str, object]:
    return {
        "neighbors": [
            neighbor_json(p, p.services) for p in peers if include_unreachable or p.reachable
        ]
    }


async def neighbors(request: Request) -> Response:
    only_params(request, ["all"])
    include_unreachable = query_flag(request, "all")
    name = "neighbors.all" if include_unreachable else "neighbors"
    body = state_of(request).view.peers_body(
        name, lambda peers: _neighbors(peers, include_unreachable)
    )
    return json_response(body)


def _search_criteria(request: Request) -> tuple[str | None, dict[str, str]]:
    stype: str | None = None
    attrs: dict[str, str] = {}
    for key, value in request.query.items():
        if key == "type":
            if stype is not None:
                raise ValidationError("type", "given more than once")
            if not value:
                raise ValidationError("type", "must not be empty")
            stype = value
        elif key.startswith("attr.") and len(key) > len("attr."):
            name = key[len("attr.") :]
            if name in attrs:
                raise ValidationError(key, "given more than once")
            attrs[name] = value
        else:
            raise ValidationError(
                key, "unknown query parameter (known: type, attr.KEY for any attribute KEY)"
            )
    if stype is None and not attrs:
        raise ValidationError("type", "give at least one criterion: type=T or attr.KEY=VALUE")
    return stype, attrs


async def search(request: Request) -> Response:
    stype, attrs = _search_criteria(request)
    found = []
    for peer in state_of(request).view.peers():
        if not peer.reachable:
            continue
        matching = [s for s in peer.services if s.matches(stype, attrs)]
        if matching:
            found.append(neighbor_json(peer, matching))
    return json_response({"neighbors": found})


async def history(request: Request) -> Response:
    body = state_of(request).view.peers_body(
        "history", lambda peers: {"robots": [p.to_json() for p in peers]}
    )
    return json_response(body)
