"""The fleet keyring's administration, on the unix socket only."""

from __future__ import annotations

import logging
import time

from sdfr.api.doors import over_unix_socket
from sdfr.api.handlers.request import only_params, query_flag
from sdfr.api.http import Request, Response
from sdfr.api.replies import RequestError, cannot_write_status, json_response, read_json
from sdfr.api.state import ApiState, state_of
from sdfr.config import keystore
from sdfr.config.keystore import KeyringFileError, StoredKeyring
from sdfr.daemon.channel import notify_discovery
from sdfr.errors import ConfigError, ValidationError
from sdfr.protocol import auth
from sdfr.store import write_reason

log = logging.getLogger("sdfr.api")


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
    only_params(request, ["open_fleet"])
    kid = request.match_info["id"]
    ring = _load_keyring(state)
    stored = keystore.remove(ring, kid, open_fleet=query_flag(request, "open_fleet"))
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
