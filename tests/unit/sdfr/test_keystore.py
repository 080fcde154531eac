"""Key files and the keyring kept in the state directory (sdfr.config.keystore), and the
state dir lock."""

from __future__ import annotations

import base64
import logging
import os
import stat
from pathlib import Path

import pytest

from sdfr.config import keystore
from sdfr.config.keystore import KeyringError, StoredKeyring
from sdfr.daemon import supervisor
from sdfr.daemon.supervisor import lock_state_dir
from sdfr.errors import ConfigError, SdfrError
from sdfr.protocol import auth
from sdfr.protocol.auth import OPEN, Keyring
from tests.support.logged import keep_daemon_logging, logged

K1 = bytes(range(32))
K2 = bytes(range(1, 33))


def write(path: Path, text: str, mode: int = 0o600) -> Path:
    path.write_text(text)
    path.chmod(mode)
    return path


def mode_of(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


# -- key files -------------------------------------------------------------------------------


def test_a_key_file_holds_one_base64_line_among_comments(tmp_path: Path) -> None:
    std = base64.b64encode(K1).decode()
    url = base64.urlsafe_b64encode(bytes([251] * 32)).decode().rstrip("=")
    assert keystore.read_key_file(write(tmp_path / "a", f"# fleet 3\n\n  {std}  \n")) == K1
    assert keystore.read_key_file(write(tmp_path / "b", url)) == bytes([251] * 32)


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("# only a comment\n", "holds no key"),
        (f"{base64.b64encode(K1).decode()}\n{base64.b64encode(K2).decode()}\n", "2 key lines"),
        ("not-base64-at-all!!\n", "not base64"),
        (base64.b64encode(b"short").decode(), "5 bytes, not 32"),
    ],
)
def test_a_bad_key_file_is_named_with_what_is_wrong(tmp_path: Path, text: str, says: str) -> None:
    path = write(tmp_path / "fleet.key", text)
    with pytest.raises(ConfigError, match=says) as err:
        keystore.read_key_file(path)
    assert str(path) in str(err.value)


def test_a_missing_or_unreadable_key_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="does not exist"):
        keystore.read_key_file(tmp_path / "nope")
    (tmp_path / "dir").mkdir()
    with pytest.raises(ConfigError, match="cannot read"):
        keystore.read_key_file(tmp_path / "dir")


def test_a_key_file_others_can_read_is_used_with_a_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = write(tmp_path / "k", base64.b64encode(K1).decode(), mode=0o644)
    with caplog.at_level(logging.WARNING, logger="sdfr.config.keystore"):
        assert keystore.read_key_file(path) == K1
    assert "chmod 600" in caplog.text and str(path) in caplog.text


def test_generate_writes_a_private_key_and_never_overwrites(tmp_path: Path) -> None:
    path = tmp_path / "keys" / "fleet.key"
    kid = keystore.generate_key_file(path)
    assert mode_of(path) == 0o600
    key = keystore.read_key_file(path)
    assert auth.key_id(key) == kid and kid in path.read_text().splitlines()[0]
    with pytest.raises(ConfigError, match="exists already"):
        keystore.generate_key_file(path)
    assert keystore.read_key_file(path) == key
    other = keystore.generate_key_file(path, force=True)
    assert other != kid and mode_of(path) == 0o600
    assert auth.key_id(keystore.read_key_file(path)) == other


# -- the keyring -----------------------------------------------------------------------------


def test_the_keyring_round_trips_privately(tmp_path: Path) -> None:
    assert keystore.load(tmp_path) == StoredKeyring()
    stored = StoredKeyring(Keyring.of([K1, K2], primary=K2, mode="sign"), {auth.key_id(K1): 100.0})
    keystore.save(tmp_path, stored)
    assert mode_of(keystore.keyring_path(tmp_path)) == 0o600
    assert keystore.load(tmp_path) == stored
    assert keystore.load_keyring(tmp_path) == stored.keyring
    assert not list(tmp_path.glob(".*.tmp"))


@pytest.mark.parametrize(
    "text",
    [
        "{not json",
        '{"version": 2, "mode": "enforce", "keys": []}',
        '{"version": 1, "mode": "lax", "keys": []}',
        '{"version": 1, "mode": "enforce", "primary": "00000000", "keys": '
        f'[{{"id": "00000000", "key": "{base64.b64encode(K1).decode()}"}}]}}',
    ],
)
def test_a_damaged_keyring_is_named(tmp_path: Path, text: str) -> None:
    write(keystore.keyring_path(tmp_path), text)
    with pytest.raises(SdfrError, match=r"keyring\.json is damaged"):
        keystore.load(tmp_path)


def key_file(tmp_path: Path, key: bytes, name: str = "fleet.key") -> Path:
    return write(tmp_path / name, base64.b64encode(key).decode() + "\n")


def test_seed_without_any_key_is_an_open_fleet(tmp_path: Path) -> None:
    assert keystore.seed_keyring(tmp_path, None, None) == OPEN
    assert not keystore.keyring_path(tmp_path).exists()


def test_seed_takes_the_key_file_into_an_empty_keyring(tmp_path: Path) -> None:
    state = tmp_path / "state"
    ring = keystore.seed_keyring(state, key_file(tmp_path, K1), None)
    assert ring == Keyring.of([K1], mode="enforce")
    assert keystore.load_keyring(state) == ring
    other = tmp_path / "other"
    assert keystore.seed_keyring(other, key_file(tmp_path, K1), "accept").mode == "accept"


def test_seed_keeps_a_keyring_a_rotation_changed(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    state = tmp_path / "state"
    keystore.save(state, StoredKeyring(Keyring.of([K2], mode="enforce")))
    with caplog.at_level(logging.WARNING, logger="sdfr.config.keystore"):
        ring = keystore.seed_keyring(state, key_file(tmp_path, K1), None)
    assert ring == Keyring.of([K2])  # the stored keyring wins over a stale key_file
    assert "update key_file" in caplog.text
    with pytest.raises(ConfigError, match="auth"):
        keystore.seed_keyring(state, None, "lax")


@pytest.mark.parametrize(
    ("live", "configured"), [("enforce", "sign"), ("enforce", "accept"), ("sign", "accept")]
)
def test_a_configured_mode_never_weakens_a_live_keyring(
    tmp_path: Path, live: str, configured: str
) -> None:
    """`sdfr keys mode enforce` on the running daemon, then a restart with an older `auth` in
    the config: the keyring keeps its mode, and the daemon says why and how to change it."""
    state = tmp_path / "state"
    keystore.save(state, StoredKeyring(Keyring.of([K1], mode=live)))
    before = keystore.keyring_path(state).read_bytes()
    with logged("sdfr.config.keystore", level=logging.WARNING) as said:
        ring = keystore.seed_keyring(state, key_file(tmp_path, K1), configured)
    assert ring.mode == live
    assert keystore.load_keyring(state).mode == live
    assert keystore.keyring_path(state).read_bytes() == before  # not rewritten
    [warning] = said
    assert f"auth = {configured}" in warning and f"mode {live}" in warning
    assert f"sdfr keys mode {configured}" in warning


def test_sdfrd_started_with_an_older_auth_keeps_enforce_and_says_so(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The whole start: a robot put in enforce live, restarted with auth = "accept" (left from
    the migration) in its configuration file."""
    state = tmp_path / "state"
    keystore.save(state, StoredKeyring(Keyring.of([K1], mode="accept")))
    keystore.save(state, keystore.set_mode(keystore.load(state), "enforce"))  # sdfr keys mode
    config = tmp_path / "sdfrd.toml"
    config.write_text(f'[sdfrd]\nfleet = 7\nstate_dir = "{state}"\nauth = "accept"\n')
    keep_daemon_logging(monkeypatch)
    monkeypatch.setattr(supervisor.Supervisor, "run", lambda self: 0)
    with logged("sdfr", "sdfrd") as said:
        assert supervisor.main(["--config", str(config), "--iface", "lo", "--robot-id", "r1"]) == 0
    assert keystore.load_keyring(state).mode == "enforce"
    [warning] = [line for line in said if "auth = accept" in line]
    assert "mode enforce" in warning and "sdfr keys mode accept" in warning
    assert any("keyed (enforce, signing with" in line for line in said)


@pytest.mark.parametrize(
    ("live", "configured"), [("accept", "sign"), ("accept", "enforce"), ("sign", "enforce")]
)
def test_a_stronger_configured_mode_raises_the_keyring(
    tmp_path: Path, live: str, configured: str
) -> None:
    state = tmp_path / "state"
    keystore.save(state, StoredKeyring(Keyring.of([K1], mode=live)))
    assert keystore.seed_keyring(state, None, configured).mode == configured
    assert keystore.load_keyring(state).mode == configured


def test_a_configured_mode_without_any_key_is_said_to_leave_the_fleet_open(tmp_path: Path) -> None:
    with logged("sdfr.config.keystore", level=logging.WARNING) as said:
        assert keystore.seed_keyring(tmp_path, None, "enforce") == OPEN
    [warning] = said
    assert "auth = enforce" in warning and "the fleet is open" in warning
    assert not keystore.keyring_path(tmp_path).exists()


def test_install_use_remove_and_mode(tmp_path: Path) -> None:
    k1, k2 = auth.key_id(K1), auth.key_id(K2)
    stored, added = keystore.install(StoredKeyring(), K1, 10.0)
    # A robot of an open fleet that gets its first key keeps talking to its unkeyed peers.
    assert added and stored.keyring == Keyring.of([K1], mode="accept")
    assert stored.installed == {k1: 10.0}
    again, added = keystore.install(stored, K1, 20.0)
    assert not added and again == stored
    stored, added = keystore.install(keystore.set_mode(stored, "enforce"), K2, 30.0)
    assert added and stored.keyring.primary == k1 and stored.keyring.mode == "enforce"
    stored = keystore.use(stored, k2)
    assert stored.keyring.primary == k2
    with pytest.raises(KeyringError, match="is the one this robot signs with") as err:
        keystore.remove(stored, k2)
    assert err.value.status == 409
    stored = keystore.remove(stored, k1)
    assert set(stored.keyring.keys) == {k2} and set(stored.installed) == {k2}
    for op in (keystore.use, keystore.remove):
        with pytest.raises(KeyringError, match="no key") as err:
            op(stored, "deadbeef")
        assert err.value.status == 404
    with pytest.raises(KeyringError) as err:
        keystore.set_mode(stored, "lax")
    assert err.value.status == 422
    with pytest.raises(KeyringError, match="install") as err:
        keystore.set_mode(StoredKeyring(), "sign")
    assert err.value.status == 409


# -- one daemon per state directory ----------------------------------------------------------


def test_one_daemon_per_state_dir(tmp_path: Path) -> None:
    fd = lock_state_dir(tmp_path)
    try:
        with pytest.raises(SdfrError, match=rf"in use by another sdfrd \(pid {os.getpid()}\)"):
            lock_state_dir(tmp_path)
    finally:
        os.close(fd)
    os.close(lock_state_dir(tmp_path))  # free again once the holder is gone


# -- more corners ------------------------------------------------------------------------------


def test_key_file_errors_name_the_path(tmp_path: Path) -> None:
    missing = tmp_path / "missing.key"
    with pytest.raises(ConfigError, match="does not exist") as err:
        keystore.read_key_file(missing)
    assert str(missing) in str(err.value)
    binary = tmp_path / "binary.key"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ConfigError, match="not text") as err:
        keystore.read_key_file(binary)
    assert str(binary) in str(err.value)
    padded = write(tmp_path / "padded", base64.urlsafe_b64encode(K2).decode() + "\n")
    assert keystore.read_key_file(padded) == K2  # urlsafe with its padding kept


def test_parse_key_accepts_whitespace_and_both_alphabets() -> None:
    text = base64.b64encode(bytes([250] * 32)).decode()  # has + and / in it
    assert "+" in text or "/" in text
    spaced = text[:10] + " \n" + text[10:]
    assert keystore.parse_key(spaced) == bytes([250] * 32)
    assert keystore.parse_key(text.replace("+", "-").replace("/", "_").rstrip("=")) == bytes(
        [250] * 32
    )
    with pytest.raises(ConfigError, match="no key"):
        keystore.parse_key("  \n")


def test_saving_replaces_a_too_open_keyring_file_with_a_private_one(tmp_path: Path) -> None:
    path = keystore.keyring_path(tmp_path)
    keystore.save(tmp_path, StoredKeyring(Keyring.of([K1])))
    path.chmod(0o644)
    stored = StoredKeyring(Keyring.of([K1, K2], mode="accept"), {auth.key_id(K2): 5.5})
    keystore.save(tmp_path, stored)
    assert mode_of(path) == 0o600
    assert keystore.load(tmp_path).installed == {auth.key_id(K2): 5.5}
    # The file says which key is which, and never anything but those keys.
    text = path.read_text()
    assert base64.b64encode(K1).decode() in text and '"mode": "accept"' in text


def test_a_keyring_that_cannot_be_read_is_named(tmp_path: Path) -> None:
    keystore.keyring_path(tmp_path).mkdir()
    with pytest.raises(SdfrError, match="cannot read") as err:
        keystore.load(tmp_path)
    assert "keyring.json" in str(err.value)


def test_seed_with_the_key_file_already_in_the_keyring_is_quiet(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    state = tmp_path / "state"
    keystore.save(state, StoredKeyring(Keyring.of([K1, K2], primary=K2, mode="sign")))
    before = keystore.keyring_path(state).stat().st_mtime_ns
    with caplog.at_level(logging.WARNING, logger="sdfr.config.keystore"):
        ring = keystore.seed_keyring(state, key_file(tmp_path, K1), "sign")
    assert ring == Keyring.of([K1, K2], primary=K2, mode="sign")
    assert "update key_file" not in caplog.text
    assert keystore.keyring_path(state).stat().st_mtime_ns == before  # same mode: not rewritten


def test_seed_reports_a_bad_key_file_even_with_an_empty_keyring(tmp_path: Path) -> None:
    bad = write(tmp_path / "bad.key", "nope\n")
    with pytest.raises(ConfigError) as err:
        keystore.seed_keyring(tmp_path / "state", bad, None)
    assert str(bad) in str(err.value)
    assert not keystore.keyring_path(tmp_path / "state").exists()


def test_later_keys_keep_the_primary_and_mode_of_an_accepting_keyring() -> None:
    stored, _ = keystore.install(StoredKeyring(), K1, 1.0)
    stored, added = keystore.install(stored, K2, 2.0)
    assert added and stored.keyring.primary == auth.key_id(K1)
    assert stored.keyring.mode == "accept"
    assert stored.installed == {auth.key_id(K1): 1.0, auth.key_id(K2): 2.0}
    assert keystore.set_mode(stored, "sign").keyring.mode == "sign"


def test_save_keyring_keeps_the_install_times_of_keys_it_keeps(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    k1, k2 = auth.key_id(K1), auth.key_id(K2)
    keystore.save_keyring(tmp_path, Keyring.of([K1], mode="sign"), {k1: 1.0, "gone": 9.0})
    stored = keystore.load(tmp_path)
    assert stored == StoredKeyring(Keyring.of([K1], mode="sign"), {k1: 1.0})
    assert mode_of(keystore.keyring_path(tmp_path)) == 0o600
    # Without times: the key already there keeps its time, the new one is stamped now.
    monkeypatch.setattr(keystore.time, "time", lambda: 50.0)
    keystore.save_keyring(tmp_path, Keyring.of([K1, K2], primary=K2, mode="enforce"))
    stored = keystore.load(tmp_path)
    assert stored.keyring == Keyring.of([K1, K2], primary=K2, mode="enforce")
    assert stored.installed == {k1: 1.0, k2: 50.0}
    assert keystore.load_keyring(tmp_path) == stored.keyring
    # Over a damaged keyring (being replaced): every key is stamped now.
    keystore.keyring_path(tmp_path).write_text("{")
    keystore.save_keyring(tmp_path, Keyring.of([K2]))
    assert keystore.load(tmp_path).installed == {k2: 50.0}


def test_a_failed_write_leaves_no_half_written_key(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "fleet.key"

    def disk_full(fd: int) -> None:
        raise OSError(28, "No space left on device")

    with monkeypatch.context() as m:
        m.setattr(keystore.os, "fsync", disk_full)
        with pytest.raises(ConfigError, match=f"cannot write {path}: No space left on device"):
            keystore.generate_key_file(path)
    assert list(tmp_path.iterdir()) == []  # so trying again needs no --force
    kid = keystore.generate_key_file(path)
    with monkeypatch.context() as m:
        m.setattr(keystore.os, "fsync", disk_full)
        with pytest.raises(ConfigError, match="No space left"):
            keystore.generate_key_file(path, force=True)
        with pytest.raises(keystore.KeyringFileError, match="keyring: cannot write") as err:
            keystore.save(tmp_path, StoredKeyring(Keyring.of([K1])))
        assert err.value.errno == 28  # the API answers 507 for it
    # The old key is intact, and no temporary file is left behind.
    assert auth.key_id(keystore.read_key_file(path)) == kid
    assert [p.name for p in tmp_path.iterdir()] == ["fleet.key"]


def test_a_replacement_never_follows_a_planted_link(tmp_path: Path) -> None:
    """In a directory others can write to, a link where the temporary file might go must
    not make root overwrite what it points to."""
    victim = write(tmp_path / "victim", "precious\n", mode=0o644)
    path = tmp_path / "fleet.key"
    keystore.generate_key_file(path)
    for pid in range(os.getpid() - 2, os.getpid() + 3):  # the names a pid-based one would use
        (tmp_path / f".fleet.key.{pid}.tmp").symlink_to(victim)
    kid = keystore.generate_key_file(path, force=True)
    assert victim.read_text() == "precious\n"
    assert auth.key_id(keystore.read_key_file(path)) == kid and mode_of(path) == 0o600
