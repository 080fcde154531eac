"""Seals, key ids, keyrings and replay windows (sdfr.protocol.auth), on bytes alone."""

from __future__ import annotations

import secrets

import pytest
from hypothesis import given
from hypothesis import strategies as st

from sdfr import wire
from sdfr.protocol import auth
from sdfr.protocol.auth import OPEN, Keyring, ReplayWindow, Sealed
from sdfr.records.model import Service
from sdfr.wire import MAX_DATAGRAM, Alive, Origin, Reject, Update

KEY = bytes(range(32))
OTHER = bytes(range(1, 33))
ORIGIN = Origin(3, "robot-7", 1700, 42, "0123456789abcdef")
ALIVE = wire.encode(Alive(ORIGIN, "http://10.3.0.7:8701/description.json", 30))


def test_key_id_names_a_key_and_is_stable() -> None:
    assert auth.key_id(KEY) == auth.key_id(bytes(KEY))
    assert auth.key_id(KEY) != auth.key_id(OTHER)
    assert len(auth.key_id(KEY)) == 8 and int(auth.key_id(KEY), 16) >= 0


def test_a_sealed_datagram_checks_out_and_still_decodes() -> None:
    ring = Keyring.of([KEY])
    sealed = auth.seal(ALIVE, KEY, 7)
    assert auth.check(sealed, ring) == Sealed(auth.key_id(KEY), 7)
    # The seal is the last header line; the codec reads the datagram as before.
    assert sealed.count(b"X-SDFR-AUTH: ") == 1 and sealed.endswith(b"\r\n\r\n")
    assert wire.decode(sealed) == wire.decode(ALIVE)
    assert len(sealed) - len(ALIVE) <= wire.SEAL_RESERVE


def test_a_sealed_update_keeps_its_body() -> None:
    svc = Service("cam", "camera", "sensor.camera", attributes={"fps": 30})
    data = wire.encode(Update(ORIGIN, "http://x/", 30, 0, 1, (svc,)))
    sealed = auth.seal(data, KEY, 1)
    assert auth.check(sealed, Keyring.of([KEY])) == Sealed(auth.key_id(KEY), 1)
    assert wire.decode(sealed) == wire.decode(data)


@pytest.mark.parametrize("where", ["header", "boot", "body", "counter", "mac"])
def test_any_change_breaks_the_seal(where: str) -> None:
    svc = Service("cam", "camera", "sensor.camera")
    data = auth.seal(wire.encode(Update(ORIGIN, "http://x/", 30, 0, 1, (svc,))), KEY, 12)
    if where == "header":
        bad = data.replace(b"X-SDFR-ROBOT: robot-7", b"X-SDFR-ROBOT: robot-8")
    elif where == "boot":
        bad = data.replace(b"BOOTID.UPNP.ORG: 1700", b"BOOTID.UPNP.ORG: 1701")
    elif where == "body":
        bad = data.replace(b'"camera"', b'"camerb"')
    elif where == "counter":
        bad = data.replace(b" 12 ", b" 13 ")
    else:
        at = data.index(b"\r\n", data.index(b"X-SDFR-AUTH: ")) - 5  # inside the mac
        bad = data[:at] + (b"A" if data[at : at + 1] != b"A" else b"B") + data[at + 1 :]
    assert bad != data
    got = auth.check(bad, Keyring.of([KEY]))
    assert isinstance(got, Reject) and got.reason == "bad-mac"


def test_unknown_and_retired_keys_are_named() -> None:
    sealed = auth.seal(ALIVE, OTHER, 1)
    got = auth.check(sealed, Keyring.of([KEY]))
    assert isinstance(got, Reject) and got.reason == "unknown-key"
    assert auth.key_id(OTHER) in got.detail
    # A keyless robot cannot check a seal: it does not take the datagram either.
    got = auth.check(sealed, OPEN)
    assert isinstance(got, Reject) and got.reason == "unknown-key"


def test_unsigned_datagrams_by_mode() -> None:
    assert auth.check(ALIVE, OPEN) is None
    assert auth.check(ALIVE, Keyring.of([KEY], mode="accept")) is None
    assert auth.check(ALIVE, Keyring.of([KEY], mode="sign")) is None
    got = auth.check(ALIVE, Keyring.of([KEY], mode="enforce"))
    assert isinstance(got, Reject) and got.reason == "unsigned"


def test_a_seal_not_last_or_malformed_is_rejected() -> None:
    sealed = auth.seal(ALIVE, KEY, 5)
    line_at = sealed.index(b"X-SDFR-AUTH")
    line = sealed[line_at : sealed.index(b"\r\n", line_at) + 2]
    moved = sealed.replace(line, b"").replace(b"HOST:", line + b"HOST:")
    for bad in (
        moved,
        sealed.replace(b" 5 ", b" five "),
        sealed.replace(b" 5 ", b" 0 "),
        sealed.replace(b" 5 ", b" 5 extra "),
        sealed.replace(auth.key_id(KEY).encode(), b"XYZ"),
    ):
        got = auth.check(bad, Keyring.of([KEY]))
        assert isinstance(got, Reject) and got.reason == "bad-seal", bad


@given(st.binary(max_size=MAX_DATAGRAM + 50))
def test_check_never_raises(data: bytes) -> None:
    got = auth.check(data, Keyring.of([KEY]))
    assert got is None or isinstance(got, Reject | Sealed)
    auth.check(b"X-SDFR-AUTH: " + data, Keyring.of([KEY]))


def test_seal_refuses_what_cannot_be_sealed() -> None:
    with pytest.raises(ValueError):
        auth.seal(b"not a datagram", KEY, 1)
    with pytest.raises(ValueError):
        auth.seal(ALIVE, KEY, 0)


def test_keyring_validates_itself() -> None:
    ring = Keyring.of([KEY, OTHER], primary=OTHER, mode="sign")
    assert ring.primary == auth.key_id(OTHER) and set(ring.keys) == {
        auth.key_id(KEY),
        auth.key_id(OTHER),
    }
    assert ring.signs and ring.accepts_unsigned
    assert not OPEN.signs and OPEN.accepts_unsigned and not OPEN.keyed
    assert not Keyring.of([KEY], mode="accept").signs
    with pytest.raises(ValueError, match="mode"):
        Keyring.of([KEY], mode="lax")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="primary"):
        Keyring({auth.key_id(KEY): KEY}, primary=auth.key_id(OTHER))
    with pytest.raises(ValueError, match="does not name"):
        Keyring({"00000000": KEY}, primary="00000000")
    with pytest.raises(ValueError, match="bytes"):
        Keyring({auth.key_id(b"short"): b"short"}, primary=auth.key_id(b"short"))


def test_replay_window() -> None:
    w = ReplayWindow()
    assert w.fresh(5, 1)
    w.accept(5, 1)
    assert not w.fresh(5, 1)
    for ctr in (3, 2, 10):
        assert w.fresh(5, ctr)
        w.accept(5, ctr)
        assert not w.fresh(5, ctr)
    assert w.fresh(5, 9) and w.fresh(5, 4)  # late but unseen
    w.accept(5, 200)
    assert not w.fresh(5, 200 - auth.WINDOW)  # too late to tell: treated as a replay
    assert w.fresh(5, 200 - auth.WINDOW + 1)
    assert not w.fresh(5, 10)
    assert w.fresh(6, 1)  # another boot is another sender
    w.accept(6, 1)
    assert not w.fresh(6, 1) and w.fresh(6, 2)


@given(st.lists(st.integers(1, 300), max_size=200))
def test_replay_window_never_accepts_twice(counters: list[int]) -> None:
    w = ReplayWindow()
    accepted: set[int] = set()
    for ctr in counters:
        if w.fresh(1, ctr):
            assert ctr not in accepted
            w.accept(1, ctr)
            accepted.add(ctr)


def test_sealing_costs() -> None:
    key = secrets.token_bytes(32)
    sealed = auth.seal(ALIVE, key, 2**53, to="robot-8", sender="10.3.0.7")
    assert len(sealed) - len(ALIVE) == auth.SEAL_LINE_MAX <= wire.SEAL_RESERVE


def test_a_seal_is_bound_to_its_recipient_and_its_senders_address() -> None:
    """A unicast sealed for one robot is refused by another, before any MAC ("not-for-me");
    a datagram arriving from another address than its sender sealed is refused ("relayed");
    a multicast is for every robot of the fleet, from its sender's address only."""
    ring = Keyring.of([KEY])
    unicast = auth.seal(ALIVE, KEY, 3, to="robot-8", sender="10.3.0.7")
    assert auth.check(unicast, ring, me="robot-8", src="10.3.0.7") == Sealed(
        auth.key_id(KEY), 3, fleet=False
    )
    other = auth.check(unicast, ring, me="robot-9", src="10.3.0.7")
    assert isinstance(other, Reject) and other.reason == "not-for-me"
    relayed = auth.check(unicast, ring, me="robot-8", src="10.3.0.66")
    assert isinstance(relayed, Reject) and relayed.reason == "relayed"
    multicast = auth.seal(ALIVE, KEY, 4, sender="10.3.0.7")
    assert auth.check(multicast, ring, me="robot-9", src="10.3.0.7") == Sealed(
        auth.key_id(KEY), 4, fleet=True
    )
    moved = auth.check(multicast, ring, me="robot-9", src="10.3.0.66")
    assert isinstance(moved, Reject) and moved.reason == "relayed"
    # The hints only save work: rewriting them to match does not get past the MAC.
    forged = multicast.replace(b"X-SDFR-AUTH: ", b"X-SDFR-AUTH: ")
    line_at = forged.index(b"X-SDFR-AUTH: ")
    route_at = forged.index(b" ", forged.index(b" ", line_at + 13) + 1) + 1
    tag = forged[route_at + 2 : route_at + 6]
    want = auth.seal(ALIVE, KEY, 4, sender="10.3.0.66")
    want_tag = want[want.index(b"*:") + 2 : want.index(b"*:") + 6]
    forged = forged.replace(b"*:" + tag, b"*:" + want_tag)
    got = auth.check(forged, ring, me="robot-9", src="10.3.0.66")
    assert isinstance(got, Reject) and got.reason == "bad-mac"
