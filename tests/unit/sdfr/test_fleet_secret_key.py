"""One secret for link and discovery: a fleet with a WiFi secret and no key_file signs its
datagrams with a key derived from that secret (HKDF-SHA256, RFC 5869)."""

from __future__ import annotations

import base64
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from sdfr.config import keystore
from sdfr.config.keystore import KeySource, StoredKeyring
from sdfr.daemon import supervisor
from sdfr.host import wifi
from sdfr.protocol import auth
from sdfr.protocol.auth import Keyring
from tests.support.logged import keep_daemon_logging, logged

SECRET = "correct horse battery staple"
K1 = bytes(range(32))


def _hex(text: str) -> bytes:
    return bytes.fromhex("".join(text.split()))


# RFC 5869 appendix A, the SHA-256 cases: (IKM, salt, info, L, PRK, OKM).
RFC5869 = {
    "A.1 basic": (
        _hex("0b" * 22),
        _hex("000102030405060708090a0b0c"),
        _hex("f0f1f2f3f4f5f6f7f8f9"),
        42,
        _hex("077709362c2e32df0ddc3f0dc47bba63 90b6c73bb50f9c3122ec844ad7c2b3e5"),
        _hex(
            "3cb25f25faacd57a90434f64d0362f2a 2d2d0a90cf1a5a4c5db02d56ecc4c5bf34007208d5b887185865"
        ),
    ),
    "A.2 longer inputs and outputs": (
        bytes(range(0x00, 0x50)),
        bytes(range(0x60, 0xB0)),
        bytes(range(0xB0, 0x100)),
        82,
        _hex("06a6b88c5853361a06104c9ceb35b45c ef760014904671014a193f40c15fc244"),
        _hex(
            "b11e398dc80327a1c8e7f78c596a4934 4f012eda2d4efad8a050cc4c19afa97c"
            "59045a99cac7827271cb41c65e590e09 da3275600c2f09b8367793a9aca3db71"
            "cc30c58179ec3e87c14c01d5c1f3434f 1d87"
        ),
    ),
    "A.3 zero-length salt and info": (
        _hex("0b" * 22),
        b"",
        b"",
        42,
        _hex("19ef24a32c717b167f33a91d6f648bdf 96596776afdb6377ac434c1c293ccb04"),
        _hex(
            "8da4e775a563c18f715f802a063c5a31 b8a11f5c5ee1879ec3454e5f3c738d2d9d201395faa4b61a96c8"
        ),
    ),
}


@pytest.mark.parametrize("case", list(RFC5869))
def test_hkdf_sha256_gives_the_test_vectors_of_rfc_5869(case: str) -> None:
    ikm, salt, info, length, prk, okm = RFC5869[case]
    assert wifi.hkdf_extract(salt, ikm) == prk
    assert wifi.hkdf_expand(prk, info, length) == okm
    assert wifi.hkdf_sha256(ikm, salt, info, length) == okm


def test_hkdf_refuses_a_length_it_cannot_give() -> None:
    prk = RFC5869["A.1 basic"][4]
    assert len(wifi.hkdf_expand(prk, b"", 255 * 32)) == 255 * 32
    for length in (0, -1, 255 * 32 + 1):
        with pytest.raises(ValueError, match="1 to 8160 bytes"):
            wifi.hkdf_expand(prk, b"", length)


def test_the_datagram_key_is_the_fleets_own_and_not_its_wifi_key() -> None:
    key = wifi.datagram_key(SECRET, 7)
    assert len(key) == auth.KEY_BYTES
    # As the WiFi key: surrounding whitespace (a file's line end) does not count.
    assert wifi.datagram_key(f"  {SECRET}\n", 7) == key
    # HKDF of the stretched secret (the WPA key), never of the bare secret: a sealed datagram
    # must not let anyone guess the WiFi secret faster than the WiFi's own handshake does.
    stretched = bytes.fromhex(wifi.derive_key(SECRET, 7))
    assert key == wifi.hkdf_sha256(stretched, b"sdfr-fleet-7", b"SDfR datagram key v1", 32)
    assert key != stretched
    assert key != wifi.datagram_key(SECRET, 8)
    assert key != wifi.datagram_key("another secret", 7)


# The daemon keeps OpenSSL out of its processes (sdfr.daemon.NOT_LOADED): hashlib and hmac
# fall back to CPython's own code there, and must give the same key.
WITHOUT_OPENSSL = """
import sys
from sdfr.daemon import NOT_LOADED
for name in NOT_LOADED:
    sys.modules.setdefault(name, None)
from sdfr.host import wifi
assert sys.modules["_hashlib"] is None
print(wifi.datagram_key(sys.argv[1], 7).hex())
"""


def test_the_daemon_derives_the_same_key_without_openssl() -> None:
    done = subprocess.run(
        [sys.executable, "-c", WITHOUT_OPENSSL, SECRET],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    )
    assert done.stdout.strip() == wifi.datagram_key(SECRET, 7).hex()


# -- seeding the keyring -----------------------------------------------------------------------


def test_a_key_source_seeds_only_an_empty_keyring(tmp_path: Path) -> None:
    made: list[int] = []

    def make() -> bytes:
        made.append(1)
        return K1

    source = KeySource("the test's secret", make)
    ring = keystore.seed_keyring(tmp_path / "a", None, None, source)
    assert ring == Keyring.of([K1], mode="enforce") and made == [1]
    assert keystore.load_keyring(tmp_path / "a") == ring
    # A keyring with keys is authoritative: the source is not even asked.
    other = tmp_path / "b"
    keystore.save(other, StoredKeyring(Keyring.of([bytes(32)], mode="sign")))
    assert keystore.seed_keyring(other, None, None, source) == Keyring.of([bytes(32)], mode="sign")
    assert made == [1]
    # key_file wins over the source.
    key_file = tmp_path / "fleet.key"
    key_file.write_text(base64.b64encode(bytes(range(1, 33))).decode() + "\n")
    key_file.chmod(0o600)
    ring = keystore.seed_keyring(tmp_path / "c", key_file, "sign", source)
    assert ring == Keyring.of([bytes(range(1, 33))], mode="sign") and made == [1]


def _start(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, state: str, *extra: str) -> Keyring:
    """sdfrd's start on `lo` (not wireless: the radio is left alone) until its layers would
    run; the keyring it leaves in its state directory."""

    def no_radio(*args: object, **kw: object) -> None:
        raise AssertionError("sdfrd touched the radio")

    monkeypatch.setattr(wifi, "apply", no_radio)
    monkeypatch.setattr(supervisor.Supervisor, "run", lambda self: 0)
    keep_daemon_logging(monkeypatch)
    state_dir = tmp_path / state
    argv = ["--iface", "lo", "--robot-id", state, "--fleet", "7", "--state-dir", str(state_dir)]
    assert supervisor.main([*argv, *extra]) == 0
    path = keystore.keyring_path(state_dir)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    return keystore.load_keyring(state_dir)


@pytest.fixture
def secret_file(tmp_path: Path) -> Path:
    path = tmp_path / "fleet.secret"
    path.write_text(SECRET + "\n")
    path.chmod(0o600)
    return path


def test_a_fleet_with_a_wifi_secret_file_and_no_key_file_starts_keyed(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    secret_file: Path,
) -> None:
    with logged("sdfr", "sdfrd") as said:
        r1 = _start(tmp_path, monkeypatch, "r1", "--wifi-secret-file", str(secret_file))
    text = "\n".join(said)
    r2 = _start(tmp_path, monkeypatch, "r2", "--wifi-secret-file", str(secret_file))
    key = wifi.datagram_key(SECRET, 7)
    assert r1 == r2 == Keyring.of([key], mode="enforce")  # both robots: one key, enforced
    kid = auth.key_id(key)
    assert f"key {kid} derived from the WiFi secret ({secret_file})" in text
    assert f"keyed (enforce, signing with {kid})" in text
    assert base64.b64encode(key).decode() not in text and key.hex() not in text


def test_the_configured_auth_mode_seeds_the_derived_keyring(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, secret_file: Path
) -> None:
    ring = _start(
        tmp_path, monkeypatch, "r1", "--wifi-secret-file", str(secret_file), "--auth", "accept"
    )
    assert ring == Keyring.of([wifi.datagram_key(SECRET, 7)], mode="accept")


def test_an_inline_wifi_secret_derives_the_same_key(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    ring = _start(tmp_path, monkeypatch, "r1", "--wifi-secret", SECRET)
    assert ring == Keyring.of([wifi.datagram_key(SECRET, 7)], mode="enforce")


def test_key_file_wins_over_the_wifi_secret(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, secret_file: Path
) -> None:
    key_file = tmp_path / "fleet.key"
    key_file.write_text(base64.b64encode(K1).decode() + "\n")
    key_file.chmod(0o600)
    ring = _start(
        tmp_path,
        monkeypatch,
        "r1",
        "--wifi-secret-file",
        str(secret_file),
        "--key-file",
        str(key_file),
    )
    assert ring == Keyring.of([K1], mode="enforce")


def test_without_any_secret_the_fleet_stays_open(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(supervisor.Supervisor, "run", lambda self: 0)
    keep_daemon_logging(monkeypatch)
    state_dir = tmp_path / "r1"
    argv = ["--iface", "lo", "--robot-id", "r1", "--state-dir", str(state_dir)]
    assert supervisor.main(argv) == 0
    assert not keystore.keyring_path(state_dir).exists()
