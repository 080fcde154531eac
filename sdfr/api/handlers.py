"""The REST handlers: local registrations, what discovery found, this robot, the keyring."""

from __future__ import annotations

import contextlib
import json
import logging
import re
import secrets
import time
from collections.abc import Iterable
from dataclasses import replace

from sdfr import __version__, auth, keystore, wire
from sdfr.api.doors import over_unix_socket
from sdfr.api.http import Request, Response, StreamResponse
from sdfr.api.leases import TTL_MAX, TTL_MIN
from sdfr.api.replies import RequestError, cannot_write_status, json_response, read_json
from sdfr.api.state import (
    FAILING_AFTER,
    ApiState,
    DiscoveryState,
    neighbor_json,
    notify_discovery,
    state_of,
)
from sdfr.errors import ConfigError, ValidationError
from sdfr.keystore import KeyringFileError, StoredKeyring
from sdfr.model import PeerRecord, Service
from sdfr.status import DiscoveryStatus
from sdfr.store import Add, Caller, Lease, NotOwner, Remove, Renew, hash_token, write_reason
from sdfr.wire import check_service_fits

log = logging.getLogger("sdfr.api")


# -- owners ------------------------------------------------------------------------------------

#: The header a program sends its owner token in.
OWNER_HEADER = "X-SDFR-Owner"
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


# -- handlers: local registrations -------------------------------------------------------------


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


# -- handlers: what discovery found ------------------------------------------------------------


def _only_params(request: Request, allowed: Iterable[str]) -> None:
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


def _flag(request: Request, name: str) -> bool:
    raw = request.query.get(name)
    if raw is None:
        return False
    if raw not in FLAG_VALUES:
        raise ValidationError(name, "must be 1/0, true/false or yes/no")
    return FLAG_VALUES[raw]


def _neighbors(peers: list[PeerRecord], include_unreachable: bool) -> dict[str, object]:
    return {
        "neighbors": [
            neighbor_json(p, p.services) for p in peers if include_unreachable or p.reachable
        ]
    }


async def neighbors(request: Request) -> Response:
    _only_params(request, ["all"])
    include_unreachable = _flag(request, "all")
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


# -- handlers: this robot ----------------------------------------------------------------------


def _discovery_json(disc: DiscoveryState) -> dict[str, object]:
    s = disc.status
    return {
        "up": disc.up,
        "heartbeat_age": disc.heartbeat_age,
        "pid": None if s is None else s.pid,
        "iface": None if s is None else s.iface,
        "started": None if s is None else s.started,
        "announced_version": None if s is None else s.version,
        "peers_reachable": None if s is None else s.peers_reachable,
        "peers_known": None if s is None else s.peers_known,
    }


async def self_info(request: Request) -> Response:
    state = state_of(request)
    await state.fresh_status()
    disc = state.discovery()
    version, services = state.view.local()
    rec = disc.status
    return json_response(
        {
            "robot_id": state.cfg.robot_id or (None if rec is None else rec.robot_id),
            "fleet": state.cfg.fleet,
            "iface": state.cfg.iface,
            "address": "" if rec is None else rec.address,
            "boot_id": None if rec is None else rec.boot_id,
            "version": version,
            "location": None if rec is None else rec.location,
            "software": f"sdfr/{__version__}",
            "services": [s.to_json() for s in services],
            "discovery": _discovery_json(disc),
        }
    )


def discovery_error(status: DiscoveryStatus) -> str | None:
    """Why the discovery layer, though alive, is failing (None when it is not): its callbacks
    failed FAILING_AFTER times within a minute, or it cannot announce our services."""
    errors = status.errors
    if errors.persistent:
        return errors.persistent
    if errors.recent >= FAILING_AFTER and errors.last is not None:
        return errors.last
    return None


def health_warnings(status: DiscoveryStatus, now: float | None = None) -> list[str]:
    """What an operator should look at while the daemon is up."""
    out = []
    conflict = status.robot_id_conflict
    if conflict is not None:
        ago = max(0.0, (time.time() if now is None else now) - conflict.last_seen)
        out.append(
            f"another sender claims this robot's id {status.robot_id}: {conflict.address} "
            f"(boot {conflict.boot_id}, {ago:.0f} s ago, {conflict.count} datagrams); give "
            "each daemon its own --robot-id"
        )
    for seen in status.auth.unknown:
        ago = max(0.0, (time.time() if now is None else now) - seen.last_seen)
        out.append(
            f"datagrams sealed with key {seen.id}, which the keyring does not hold, are dropped: "
            f"{seen.count} datagrams from {seen.address}, the last {ago:.0f} s ago (a robot left "
            "out of a key rotation?); give it the fleet's key, or `sdfr keys install` its key"
        )
    mode = status.auth.mode
    if mode in ("accept", "sign"):
        out.append(
            f"keyring mode {mode}: unsigned datagrams are accepted; finish with "
            "`sdfr keys mode enforce` on every robot"
        )
    return out


def state_problem(state: ApiState, disc: DiscoveryState) -> tuple[str, str] | None:
    """Why the state directory cannot be written, if it cannot: (full | read-only | error,
    message), from this layer's last failed write (until one works) or the discovery
    layer's report."""
    if state.write_problem is not None and time.time() - state.write_problem[0] < 60.0:
        return state.write_problem[1], state.write_problem[2]
    report = None if disc.status is None else disc.status.state
    if disc.up and report is not None and not report.writable:
        return report.reason or "error", report.error or ""
    return None


async def health(request: Request) -> Response:
    state = state_of(request)
    await state.fresh_status()
    disc = state.discovery()
    failing = discovery_error(disc.status) if disc.up and disc.status else None
    warnings = health_warnings(disc.status) if disc.up and disc.status else []
    cannot_write = state_problem(state, disc)
    starting = disc.up and disc.status is not None and disc.status.starting
    ok = disc.up and not starting and failing is None and cannot_write is None
    return json_response(
        {
            "status": "degraded" if not ok else "warning" if warnings else "ok",
            "api": "up",
            "discovery": ("failing" if failing else "starting" if starting else "up")
            if disc.up
            else "down",
            "discovery_heartbeat_age": disc.heartbeat_age,
            "discovery_error": failing,
            "state": "ok" if cannot_write is None else cannot_write[0],
            "state_error": None if cannot_write is None else cannot_write[1],
            "auth": None if disc.status is None else disc.status.auth.mode,
            "warnings": warnings,
        },
        status=200 if ok else 503,
    )


# -- handlers: the fleet keyring (unix socket only) --------------------------------------------


def _need_unix_socket(request: Request) -> None:
    """Key management is for whoever may open STATE_DIR/api.sock (its file mode says who),
    never for any program that can reach a TCP port."""
    if not over_unix_socket(request):
        path = state_of(request).cfg.state_dir / "api.sock"
        raise RequestError(
            403,
            f"key management is only available on the unix socket {path} "
            "(sdfr keys --state-dir DIR, or --socket PATH)",
        )


def _keys_json(state: ApiState, stored: StoredKeyring) -> dict[str, object]:
    ring = stored.keyring
    status = state.discovery().status
    received = {} if status is None else status.auth.received
    unknown = [
        {
            "id": seen.id,
            "address": seen.address,
            "count": seen.count,
            "first_seen": seen.first_seen,
            "last_seen": seen.last_seen,
        }
        for seen in (() if status is None else status.auth.unknown)
        if seen.id not in ring.keys  # (installed since)
    ]
    return {
        "mode": ring.mode if ring.keyed else "open",
        "primary": ring.primary,
        "keyed": ring.keyed,
        "ssdp_interop": auth.plain_ssdp_answered(state.cfg.ssdp_interop_wanted, ring),
        "keys": [
            {
                "id": kid,
                "primary": kid == ring.primary,
                "installed": stored.installed.get(kid),
                "received": received.get(kid, 0),
            }
            for kid in sorted(ring.keys)
        ],
        **({"unknown": unknown} if unknown else {}),
    }


def _keyring_failed(exc: KeyringFileError) -> RequestError:
    """keyring.json could not be read or written: say so, with the status a state directory
    problem gets elsewhere (507 full, 503 read-only), and 500 for a damaged file."""
    log.warning("%s", exc)
    reason = write_reason(exc.errno)
    status = 500 if reason == "error" else cannot_write_status(reason)
    return RequestError(status, str(exc), "keyring")


def _load_keyring(state: ApiState) -> StoredKeyring:
    try:
        return keystore.load(state.cfg.state_dir)
    except KeyringFileError as exc:
        raise _keyring_failed(exc) from None


def _save_keyring(state: ApiState, stored: StoredKeyring, what: str) -> None:
    try:
        keystore.save(state.cfg.state_dir, stored)
    except KeyringFileError as exc:
        raise _keyring_failed(exc) from None
    notify_discovery(state.cfg.state_dir)
    ring = stored.keyring
    signs = ring.primary if ring.signs else "no key"
    log.info("keyring: %s; mode %s, signing with %s", what, ring.mode, signs)


async def keys_list(request: Request) -> Response:
    _need_unix_socket(request)
    state = state_of(request)
    await state.fresh_status()
    return json_response(_keys_json(state, _load_keyring(state)))


async def _one_text_field(request: Request, name: str, shape: str) -> str:
    """The body `{name: "..."}` and nothing else; a 422 naming `name` otherwise."""
    obj = await read_json(request)
    if not isinstance(obj, dict) or set(obj) != {name} or not isinstance(obj[name], str):
        raise ValidationError(name, f"expected {{{name!r}: {shape}}}".replace("'", '"'))
    value: str = obj[name]
    return value


async def keys_install(request: Request) -> Response:
    _need_unix_socket(request)
    state = state_of(request)
    await state.fresh_status()
    text = await _one_text_field(request, "key", '"<base64 of 32 bytes>"')
    try:
        key = keystore.parse_key(text, "key")
    except ConfigError as exc:
        raise ValidationError("key", str(exc).removeprefix("key: ")) from None
    stored, added = keystore.install(_load_keyring(state), key, time.time())
    kid = auth.key_id(key)
    if added:
        _save_keyring(state, stored, f"key {kid} installed")
    body = {"id": kid, **_keys_json(state, stored)}
    return json_response(body, status=201 if added else 200)


async def keys_use(request: Request) -> Response:
    _need_unix_socket(request)
    state = state_of(request)
    await state.fresh_status()
    kid = request.match_info["id"]
    stored = keystore.use(_load_keyring(state), kid)
    _save_keyring(state, stored, f"signing with key {kid}")
    return json_response(_keys_json(state, stored))


async def keys_remove(request: Request) -> Response:
    _need_unix_socket(request)
    state = state_of(request)
    _only_params(request, ["open_fleet"])
    kid = request.match_info["id"]
    stored = keystore.remove(_load_keyring(state), kid, open_fleet=_flag(request, "open_fleet"))
    _save_keyring(state, stored, f"key {kid} removed")
    if not stored.keyring.keyed and state.cfg.key_file is not None:
        log.warning(
            "keyring: the fleet is open on this robot, but key_file = %s in the configuration "
            "seeds the keyring again at the next start: remove key_file",
            state.cfg.key_file,
        )
    return Response(status=204)


async def keys_mode(request: Request) -> Response:
    _need_unix_socket(request)
    state = state_of(request)
    await state.fresh_status()
    mode = await _one_text_field(request, "mode", '"accept" | "sign" | "enforce"')
    stored = keystore.set_mode(_load_keyring(state), mode)
    _save_keyring(state, stored, f"mode {mode}")
    return json_response(_keys_json(state, stored))
