"""Fleet keys on disk: key files, and the keyring a robot keeps in its state directory.

The pure keyring (which keys, which one signs, the mode) is `sdfr.protocol.auth.Keyring`; this
module reads and writes it.  A *key file* holds one key and is what an operator copies to robots
(`sdfr keys generate FILE`); the *keyring* (STATE_DIR/keyring.json, mode 0600) is what a
running daemon uses.  `key_file` seeds the keyring on the first start only: afterwards the
keyring is authoritative, since a rotation (`sdfr keys install/use/remove`) changes it live
and must survive restarts.  Owners: the supervisor seeds it; after that only the API layer
writes it, and the discovery layer reloads it when told (or when it sees it changed).
"""

from __future__ import annotations

import base64
import binascii
import contextlib
import json
import logging
import os
import secrets
import stat
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path

from sdfr.errors import ConfigError, SdfrError
from sdfr.protocol.auth import KEY_BYTES, MODES, OPEN, Keyring, Mode, key_id

log = logging.getLogger("sdfr.config.keystore")

KEYRING_NAME = "keyring.json"
FORMAT_VERSION = 1


class KeyringError(SdfrError):
    """A keyring operation that cannot be done; `status` is the HTTP answer for it."""

    def __init__(self, message: str, status: int = 409, field: str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.status = status
        self.field = field


class KeyringFileError(SdfrError):
    """STATE_DIR/keyring.json cannot be read, written or understood; `errno` when the
    system said why (ENOSPC: the disk is full, EROFS: it is read-only)."""

    def __init__(self, message: str, errno: int | None = None) -> None:
        super().__init__(message)
        self.errno = errno


class _WriteFailed(ConfigError):
    def __init__(self, path: Path, exc: OSError) -> None:
        super().__init__(f"cannot write {path}: {exc.strerror or exc}")
        self.errno = exc.errno


# -- key files -------------------------------------------------------------------------------


def parse_key(text: str, where: str = "key") -> bytes:
    """A key from its base64 text (standard or URL-safe, padding optional)."""
    raw = "".join(text.split())
    if not raw:
        raise ConfigError(f"{where}: no key (expected base64 of {KEY_BYTES} bytes)")
    try:
        std = raw.rstrip("=").replace("-", "+").replace("_", "/")
        key = base64.b64decode(std + "=" * (-len(std) % 4), validate=True)
    except (binascii.Error, ValueError):
        raise ConfigError(f"{where}: not base64 (expected base64 of {KEY_BYTES} bytes)") from None
    if len(key) != KEY_BYTES:
        raise ConfigError(f"{where}: the key is {len(key)} bytes, not {KEY_BYTES}")
    return key


def read_key_file(path: Path) -> bytes:
    """The key in a key file: one base64 line; lines starting with # and blank lines aside."""
    try:
        st = path.stat()
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(f"key_file: {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) else "not text"
        raise ConfigError(f"key_file: cannot read {path}: {reason}") from None
    lines = [ln.strip() for ln in text.splitlines()]
    keys = [ln for ln in lines if ln and not ln.startswith("#")]
    if len(keys) != 1:
        found = "no key" if not keys else f"{len(keys)} key lines"
        raise ConfigError(f"key_file: {path} holds {found}; expected exactly one base64 line")
    key = parse_key(keys[0], f"key_file: {path}")
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        log.warning(
            "key_file: %s can be read by other users (mode %o); make it chmod 600",
            path,
            stat.S_IMODE(st.st_mode),
        )
    return key


def key_text(key: bytes) -> str:
    return base64.b64encode(key).decode()


def generate_key_file(path: Path, *, force: bool = False) -> str:
    """Write a new random key to `path` (mode 0600); its key id.  Never overwrites a file
    unless `force`."""
    key = secrets.token_bytes(KEY_BYTES)
    kid = key_id(key)
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    body = f"# SDfR fleet key {kid}, generated {stamp}\n{key_text(key)}\n".encode()
    if not force and (path.exists() or path.is_symlink()):
        raise ConfigError(f"{path} exists already; not overwriting a key (use --force)")
    _write_private(path, body, exclusive=not force)
    return kid


def _write_private(path: Path, body: bytes, *, exclusive: bool) -> None:
    """Write `body` to `path`, mode 0600, durably; replace atomically unless `exclusive`.

    Nothing half-written is ever left: a failed write removes what it created.  The temporary
    file of a replacement has a random name and is created exclusively, so a link planted in
    a shared directory is never followed.
    """
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise _WriteFailed(path, exc) from None
    target = path if exclusive else path.with_name(f".{path.name}.{secrets.token_hex(8)}.tmp")
    try:
        fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        raise ConfigError(f"{path} exists already; not overwriting a key (use --force)") from None
    except OSError as exc:
        raise _WriteFailed(path, exc) from None
    try:
        with os.fdopen(fd, "wb") as out:
            out.write(body)
            out.flush()
            os.fsync(out.fileno())
        if target != path:
            os.replace(target, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            target.unlink()
        raise _WriteFailed(path, exc) from None
    try:
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError as exc:  # the file is complete; only its name may not be durable yet
        raise _WriteFailed(path, exc) from None


# -- the keyring in the state directory ------------------------------------------------------


@dataclass(frozen=True, slots=True)
class StoredKeyring:
    """The keyring as stored: the keyring itself and when each key was installed."""

    keyring: Keyring = OPEN
    installed: Mapping[str, float] = field(default_factory=dict)

    def to_json(self) -> dict[str, object]:
        ring = self.keyring
        return {
            "version": FORMAT_VERSION,
            "mode": ring.mode,
            "primary": ring.primary,
            "keys": [
                {"id": kid, "key": key_text(key), "installed": self.installed.get(kid)}
                for kid, key in sorted(ring.keys.items())
            ],
        }


def keyring_path(state_dir: Path) -> Path:
    return state_dir / KEYRING_NAME


def load(state_dir: Path) -> StoredKeyring:
    """The stored keyring; an empty one (an open fleet) when there is none."""
    path = keyring_path(state_dir)
    try:
        text = path.read_text()
    except FileNotFoundError:
        return StoredKeyring()
    except OSError as exc:
        raise KeyringFileError(
            f"keyring: cannot read {path}: {exc.strerror or exc}", exc.errno
        ) from None
    try:
        obj = json.loads(text)
        if not isinstance(obj, dict) or obj.get("version") != FORMAT_VERSION:
            raise ValueError(f"not an SDfR keyring of format {FORMAT_VERSION}")
        mode = obj.get("mode")
        if mode not in MODES:
            raise ValueError(f"mode {mode!r} is not one of {', '.join(MODES)}")
        keys: dict[str, bytes] = {}
        installed: dict[str, float] = {}
        for item in obj.get("keys", []):
            key = parse_key(str(item["key"]), "key")
            kid = key_id(key)
            if item.get("id") != kid:
                raise ValueError(f"key {item.get('id')!r} is not the key stored under it")
            keys[kid] = key
            if isinstance(item.get("installed"), int | float):
                installed[kid] = float(item["installed"])
        ring = Keyring(keys, obj.get("primary") if keys else None, mode)
    except (ValueError, KeyError, TypeError, ConfigError) as exc:
        raise KeyringFileError(
            f"keyring: {path} is damaged ({exc}); restore it, or remove it and start sdfrd "
            "with key_file"
        ) from None
    return StoredKeyring(ring, installed)


def load_keyring(state_dir: Path) -> Keyring:
    return load(state_dir).keyring


def save(state_dir: Path, stored: StoredKeyring) -> None:
    """Write the keyring (mode 0600) durably and atomically: a power cut leaves the old one or
    the new one, never a mix."""
    body = (json.dumps(stored.to_json(), indent=2) + "\n").encode()
    try:
        _write_private(keyring_path(state_dir), body, exclusive=False)
    except ConfigError as exc:
        raise KeyringFileError(f"keyring: {exc}", getattr(exc, "errno", None)) from None


def save_keyring(
    state_dir: Path, keyring: Keyring, installed: Mapping[str, float] | None = None
) -> None:
    """Write `keyring` as the stored one (see `save`).

    `installed` gives when each key was installed; without it, keys already stored keep
    their recorded time and new ones are stamped now.  Times of keys not in `keyring` are
    dropped.
    """
    if installed is None:
        try:
            before = load(state_dir).installed
        except KeyringFileError:  # a damaged keyring is being replaced: no times to keep
            before = {}
        now = time.time()
        installed = {kid: before.get(kid, now) for kid in keyring.keys}
    kept = {kid: t for kid, t in installed.items() if kid in keyring.keys}
    save(state_dir, StoredKeyring(keyring, kept))


@dataclass(frozen=True, slots=True)
class KeySource:
    """A key from elsewhere than key_file (the fleet's WiFi secret): made only to seed an
    empty keyring."""

    #: For the log: where the key comes from.
    name: str
    make: Callable[[], bytes]


#: How much each mode refuses: a configured mode is applied to a live keyring only upward.
STRENGTH: Mapping[str, int] = {"accept": 0, "sign": 1, "enforce": 2}


def seed_keyring(
    state_dir: Path, key_file: Path | None, mode: str | None, derived: KeySource | None = None
) -> Keyring:
    """At start: the keyring the daemon runs with.

    A keyring with keys is authoritative (a rotation may have replaced the key in `key_file`,
    `sdfr keys mode` may have changed its mode).  `mode` (the configuration's `auth`) seeds a
    new keyring and may raise a live one's mode (accept < sign < enforce), never lower it: a
    weaker configured mode is not applied and a warning says how to lower it live.  An empty
    keyring takes the key of `key_file`, else the `derived` one (from the WiFi secret), in
    `mode` (default enforce).  None of them: the fleet is open.
    """
    stored = load(state_dir)
    ring = stored.keyring
    if mode is not None and mode not in MODES:
        raise ConfigError(f"auth: must be one of {', '.join(MODES)}, got {mode!r}")
    if ring.keyed:
        if key_file is not None:
            key = read_key_file(key_file)
            if key_id(key) not in ring.keys:
                log.warning(
                    "key_file %s holds key %s, which the keyring in %s does not: the keyring "
                    "is used (rotated since?); update key_file",
                    key_file,
                    key_id(key),
                    keyring_path(state_dir),
                )
        if mode is not None and STRENGTH[mode] > STRENGTH[ring.mode]:
            log.info("auth: mode %s (was %s), as the configuration says", mode, ring.mode)
            stored = replace(stored, keyring=replace(ring, mode=mode))
            save(state_dir, stored)
        elif mode is not None and mode != ring.mode:
            log.warning(
                "auth = %s in the configuration is weaker than the keyring's mode %s (%s): "
                "kept %s, since a configured mode never weakens a live keyring; to weaken it "
                "run `sdfr keys mode %s` on the running daemon, else set auth = %s or leave "
                "it out of the configuration",
                mode,
                ring.mode,
                keyring_path(state_dir),
                ring.mode,
                mode,
                ring.mode,
            )
        return stored.keyring
    if key_file is None and derived is None:
        if mode is not None:
            log.warning(
                "auth = %s in the configuration, but this robot has no key (no key_file, and "
                "no key in %s): the fleet is open; set key_file or `sdfr keys install FILE`",
                mode,
                keyring_path(state_dir),
            )
        return OPEN
    if key_file is not None:
        key, source = read_key_file(key_file), str(key_file)
    else:
        assert derived is not None
        key, source = derived.make(), derived.name
        if len(key) != KEY_BYTES:
            raise ConfigError(f"{source}: made a key of {len(key)} bytes, not {KEY_BYTES}")
    new_mode: Mode = mode if mode is not None else "enforce"
    stored = StoredKeyring(Keyring.of([key], mode=new_mode), {key_id(key): time.time()})
    save(state_dir, stored)
    how = "from" if key_file is not None else "derived from"
    log.info("keyring: key %s %s %s, mode %s", key_id(key), how, source, new_mode)
    return stored.keyring


# -- changes on a running daemon (the API layer) ---------------------------------------------


def install(stored: StoredKeyring, key: bytes, now: float) -> tuple[StoredKeyring, bool]:
    """Add a key (accepted from now on, not yet used to sign); (new keyring, whether it is new).

    The first key of a robot that had none becomes its primary in mode accept: the robot
    keeps talking to its unkeyed peers until told `mode sign`, then `mode enforce`.
    """
    ring = stored.keyring
    kid = key_id(key)
    if kid in ring.keys:
        return stored, False
    keys = {**ring.keys, kid: key}
    new = Keyring(keys, ring.primary, ring.mode) if ring.keyed else Keyring(keys, kid, "accept")
    return StoredKeyring(new, {**stored.installed, kid: now}), True


def use(stored: StoredKeyring, kid: str) -> StoredKeyring:
    """Sign with key `kid` from now on."""
    ring = stored.keyring
    if kid not in ring.keys:
        raise KeyringError(f"no key {kid!r} in the keyring; `sdfr keys list` shows them", 404, "id")
    return replace(stored, keyring=Keyring(ring.keys, kid, ring.mode))


def remove(stored: StoredKeyring, kid: str, *, open_fleet: bool = False) -> StoredKeyring:
    """Stop accepting key `kid`; never the key in use (use another one first), except the
    last key with `open_fleet`, in mode accept: the way back to an open fleet."""
    ring = stored.keyring
    if kid not in ring.keys:
        raise KeyringError(f"no key {kid!r} in the keyring; `sdfr keys list` shows them", 404, "id")
    last = len(ring.keys) == 1
    if open_fleet and not last:
        raise KeyringError(
            f"key {kid} is not the last key of the keyring, the fleet stays keyed; "
            "remove the others first",
            409,
            "open_fleet",
        )
    if kid == ring.primary and not last:
        raise KeyringError(
            f"key {kid} is the one this robot signs with: `sdfr keys use` another key first",
            409,
            "id",
        )
    if last and not open_fleet:
        raise KeyringError(
            f"key {kid} is the last key: removing it opens the fleet on this robot; to do so, "
            f"`sdfr keys remove {kid} --open-fleet`",
            409,
            "id",
        )
    if last and ring.mode != "accept":
        raise KeyringError(
            f"this robot is in mode {ring.mode}: an open robot sends unsigned and drops signed "
            "datagrams, so every robot must stop signing first: `sdfr keys mode sign` on every "
            "robot, then `sdfr keys mode accept` on every robot",
            409,
            "mode",
        )
    if last:
        return StoredKeyring()
    keys = {k: v for k, v in ring.keys.items() if k != kid}
    installed = {k: v for k, v in stored.installed.items() if k != kid}
    return StoredKeyring(Keyring(keys, ring.primary, ring.mode), installed)


def set_mode(stored: StoredKeyring, mode: str) -> StoredKeyring:
    if mode not in MODES:
        raise KeyringError(f"mode must be one of {', '.join(MODES)}, not {mode!r}", 422, "mode")
    ring = stored.keyring
    if not ring.keyed:
        raise KeyringError("the keyring has no key: `sdfr keys install FILE` first", 409, "mode")
    return replace(stored, keyring=replace(ring, mode=mode))
