"""The REST handlers of local registrations: publish, unpublish, read, renew, hold, list."""

from __future__ import annotations

import contextlib
import json
import logging
import secrets
from dataclasses import replace

from sdfr import wire
from sdfr.api.handlers.request import caller, not_yours, owner_token
from sdfr.api.http import Request, Response, StreamResponse
from sdfr.api.leases import TTL_MAX, TTL_MIN
from sdfr.api.replies import RequestError, json_response, read_json
from sdfr.api.state import ApiState, state_of
from sdfr.daemon.channel import notify_discovery
from sdfr.errors import ValidationError
from sdfr.records.model import Service
from sdfr.store import Add, Caller, Lease, NotOwner, Remove, Renew
from sdfr.wire import check_service_fits

log = logging.getLogger("sdfr.api")


def _published(
    service: Service, version: int, status: int, lease: Lease | None, token: str | None
) -> Response:
    return json_response(
        {
            "id": service.id,
            "service": service.to_json(),
            "version": version,
            "ttl": None if lease is None else lease.ttl,
            "expires": None if lease is None else lease.expires,
            "owner_token": token,
        },
        status=status,
        headers={"Location": f"/services/{service.id}"},
    )


def _ttl(obj: object) -> float | None:
    """The `ttl` of a request body (taken out of it), None when it has none."""
    if not isinstance(obj, dict) or "ttl" not in obj:
        return None
    ttl = obj.pop("ttl")
    if ttl is None:
        return None
    if isinstance(ttl, bool) or not isinstance(ttl, int | float) or not TTL_MIN <= ttl <= TTL_MAX:
        raise ValidationError(
            "ttl",
            f"must be a number of seconds from {TTL_MIN:g} to {TTL_MAX:.0f} (a lease its owner "
            "renews), or null for none",
        )
    return float(ttl)


async def _published_already(
    state: ApiState, service: Service, ttl: float | None, who: Caller, token: str | None
) -> Response | None:
    """A publish under a chosen id that is stored already: the same service again by its
    owner (a client retrying after a lost answer, or publishing again after its lease ran
    out) gets 200, on disk, and its lease is set to `ttl` (renewed); by anyone else, 403;
    another service, 409."""
    stored = state.store.get_service(service.id)
    if stored is None:
        return None
    if stored != service:
        raise RequestError(
            409,
            f"service id {service.id!r} is taken by another service; choose another id, or "
            "leave id out and the robot picks one",
            "id",
        )
    result = await state.writer.write(Renew(service.id, ttl, set_ttl=True, caller=who))
    if isinstance(result, NotOwner):
        raise not_yours(service.id)
    if result is None:  # unpublished in between: publish it as new
        return None
    state.write_problem = None
    lease = state.store.lease(service.id)
    state.leases.set(lease, service.id)
    state.view.leases_changed()
    return _published(stored, state.store.local_version(), 200, lease, token)


async def publish(request: Request) -> Response:
    """POST /services: the service belongs to the owner token the request carries, or one
    made for it (answered as owner_token), and on the unix socket to its user too."""
    state = state_of(request)
    presented = owner_token(request)
    token = presented or secrets.token_urlsafe(32)
    who = caller(request, token)
    obj = await read_json(request)
    ttl = _ttl(obj)
    chosen = isinstance(obj, dict) and "id" in obj
    service = Service.from_json(obj, service_id=None if chosen else secrets.token_hex(6))
    try:
        check_service_fits(service)
    except ValidationError as exc:  # valid, but too large for the fleet to ever see
        raise RequestError(413, f"the service {exc.message}", exc.field) from None
    if chosen and (again := await _published_already(state, service, ttl, who, presented)):
        return again
    # What the fleet can never see must not be acknowledged: one announcement is at most
    # MAX_PARTS datagrams.
    needed = state.view.parts_with(service)
    if needed > wire.MAX_PARTS:
        raise RequestError(
            507,
            f"this robot's services would need {needed} update parts, more than the "
            f"{wire.MAX_PARTS} one announcement can carry; unpublish some or make them smaller",
            "services",
        )
    with state.view.reserving(service):  # checked: concurrent publishes must count it
        for _ in range(3):
            result = await state.writer.write(Add(service, ttl, who))
            if isinstance(result, int):
                break
            if chosen:  # the same id published by a request that was in flight with this one
                again = await _published_already(state, service, ttl, who, presented)
                if again is None:
                    continue  # (and unpublished since)
                return again
            service = replace(service, id=secrets.token_hex(6))  # the random id exists: another
        else:
            raise RequestError(500, "could not allocate a service id")
    state.write_problem = None
    lease = state.store.lease(service.id) if ttl is not None else None
    state.leases.set(lease, service.id)
    notify_discovery(state.cfg.state_dir)
    log.info(
        "published %s (%s, %s), version %d%s",
        service.id,
        service.name,
        service.type,
        result,
        "" if ttl is None else f", lease {ttl:g} s",
    )
    return _published(service, result, 201, lease, token)


async def unpublish(request: Request) -> Response:
    state = state_of(request)
    service_id = request.match_info["id"]
    version = await state.writer.write(Remove(service_id, caller(request, owner_token(request))))
    if version is None:
        raise RequestError(404, f"no local service with id {service_id!r}", "id")
    if isinstance(version, NotOwner):
        raise not_yours(service_id)
    state.write_problem = None
    state.leases.set(None, service_id)
    notify_discovery(state.cfg.state_dir)
    log.info("unpublished %s, version %s", service_id, version)
    return Response(status=204)


def _no_such_service(service_id: str) -> RequestError:
    return RequestError(
        404,
        f"no local service with id {service_id!r} (unpublished, or its lease ran out)",
        "id",
    )


async def get_service(request: Request) -> Response:
    state = state_of(request)
    service_id = request.match_info["id"]
    service = state.store.get_service(service_id)
    if service is None:
        raise _no_such_service(service_id)
    lease = state.store.lease(service_id)
    return _published(service, state.store.local_version(), 200, lease, None)


async def _renew(state: ApiState, service_id: str, ttl: float | None, who: Caller) -> Lease:
    result = await state.writer.write(Renew(service_id, ttl, caller=who))
    if isinstance(result, NotOwner):
        raise not_yours(service_id)
    if result is None:
        if state.store.get_service(service_id) is None:
            raise _no_such_service(service_id)
        raise RequestError(
            409,
            f"service {service_id!r} has no lease to renew; publish it with a ttl",
            "ttl",
        )
    lease = state.store.lease(service_id)
    assert lease is not None
    state.leases.set(lease, service_id)
    state.view.leases_changed()
    return lease


async def renew(request: Request) -> Response:
    """POST /services/{id}/renew: the lease runs `ttl` seconds from now again (the body may
    give another ttl); the answer says until when. Not fsynced: cheap."""
    state = state_of(request)
    service_id = request.match_info["id"]
    who = caller(request, owner_token(request))
    ttl = None
    if request.body_exists:
        obj = await read_json(request)
        if not isinstance(obj, dict) or set(obj) - {"ttl"}:
            raise ValidationError("body", 'expected nothing, or {"ttl": seconds}')
        ttl = _ttl(obj)
    lease = await _renew(state, service_id, ttl, who)
    return json_response({"id": service_id, "ttl": lease.ttl, "expires": lease.expires})


#: A held lease is renewed each time this share of its ttl has passed.
HOLD_EVERY = 1 / 3


async def hold(request: Request) -> Response:
    """POST /services/{id}/hold: renew the lease for as long as this connection stays open
    (a Server-Sent Event `renewed` each time); when it closes, the lease runs out after its
    ttl. A program that cannot run a timer keeps its services alive with one request."""
    state = state_of(request)
    service_id = request.match_info["id"]
    who = caller(request, owner_token(request))
    lease = await _renew(state, service_id, None, who)
    if "text/event-stream" not in request.headers.get("Accept", ""):
        # A client that cannot read a stream gets one renewal (as /renew), not a hang.
        return json_response({"id": service_id, "ttl": lease.ttl, "expires": lease.expires})
    resp = StreamResponse(
        headers={"Content-Type": "text/event-stream; charset=utf-8", "Cache-Control": "no-cache"}
    )
    await resp.prepare(request)
    try:
        while True:
            body = json.dumps({"id": service_id, "ttl": lease.ttl, "expires": lease.expires})
            await resp.write(f"event: renewed\ndata: {body}\n\n".encode())
            if await state.hub.closing(max(0.2, lease.ttl * HOLD_EVERY), resp.gone):
                if resp.gone.is_set():
                    raise ConnectionResetError  # the holder went away
                break  # sdfrd stops: the lease runs its ttl (a restart is quicker than that)
            try:
                lease = await _renew(state, service_id, None, who)
            except RequestError as exc:
                gone = json.dumps({"id": service_id, "error": exc.message})
                await resp.write(f"event: gone\ndata: {gone}\n\n".encode())
                break
    except ConnectionError:  # the holder went away: the lease runs out after its ttl
        log.info("hold of %s ended: its lease runs out in %g s", service_id, lease.ttl)
    with contextlib.suppress(ConnectionError):
        await resp.write_eof()
    return resp


async def list_services(request: Request) -> Response:
    return json_response(state_of(request).view.services_body())
