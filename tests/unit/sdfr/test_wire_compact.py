"""The compact wire forms (robot to robot, wire version 2) and how a robot says it reads them."""

from __future__ import annotations

import dataclasses
import zlib
from collections.abc import Callable

import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from sdfr.records.model import Service
from sdfr.wire import (
    MAX_ENCODED,
    PACKED,
    WANT_ALL,
    WIRE_COMPACT,
    WIRE_FULL,
    Alive,
    Byebye,
    Discovery,
    Origin,
    Reject,
    Response,
    Update,
    Want,
    decode,
    delta_dictionary,
    encode,
    encode_update_parts,
    last_step,
    read_step,
    unpack_delta,
)
from tests.support.wire_data import (
    LOCATION,
    ORIGIN,
    check_reject,
    header_texts,
    locations,
    noisy_services,
    origins,
    realistic_services,
    seqs,
    services,
    wants,
)

NEW = dataclasses.replace(ORIGIN, wire=WIRE_COMPACT)
compact_origins = origins.map(lambda o: dataclasses.replace(o, wire=WIRE_COMPACT))


@given(origin=compact_origins, seq=seqs, location=st.just("") | locations)
def test_compact_alive_and_byebye_round_trip(
    origin: Origin, seq: int | None, location: str
) -> None:
    alive = Alive(origin, location, 0, seq)
    data = encode(alive, compact=True)
    assert decode(data) == alive
    assert decode(data, fleet=origin.fleet) == alive
    bye = Byebye(origin)
    assert decode(encode(bye, compact=True)) == bye


@given(
    origin=compact_origins,
    st_=header_texts,
    seq=seqs,
    want=wants,
    want_version=st.none() | st.integers(0, 2**53),
    have=st.none() | st.integers(0, 2**53),
)
def test_compact_search_round_trip(
    origin: Origin,
    st_: str,
    seq: int | None,
    want: Want,
    want_version: int | None,
    have: int | None,
) -> None:
    msg = Discovery(origin, st_, 0, seq, want, want_version, multicast=False, have=have)
    assert decode(encode(msg, compact=True)) == msg


@given(origin=compact_origins, seq=st.integers(0, 2**53), ping=seqs, own_st=st.booleans())
def test_compact_ping_reply_round_trip(
    origin: Origin, seq: int, ping: int | None, own_st: bool
) -> None:
    st_ = f"uuid:{origin.robot_id}" if own_st else "urn:sdfr-org:device:robot:1"
    msg = Response(origin, st_, "", 0, seq, ping)
    data = encode(msg, compact=True)
    assert decode(data) == msg
    assert (b"\r\nST: " in data) != own_st  # the usual ST goes without saying


@given(
    origin=compact_origins,
    svcs=st.lists(services, max_size=3, unique_by=lambda s: s.id),
    removed=st.lists(st.from_regex(r"[a-z]{1,8}", fullmatch=True), max_size=3, unique=True),
    location=st.just("") | locations,
)
def test_compact_delta_round_trip(
    origin: Origin, svcs: list[Service], removed: list[str], location: str
) -> None:
    assume(origin.version > 0 and not {s.id for s in svcs} & set(removed))
    msg = Update(origin, location, 0, 0, 1, tuple(svcs), origin.version - 1, tuple(removed))
    try:
        data = encode(msg, compact=True)
    except ValueError:
        assume(False)
    assert decode(data) == msg


@pytest.mark.parametrize("make", [noisy_services, realistic_services])
def test_compact_set_in_parts_round_trips_and_keeps_location(
    make: Callable[[int], list[Service]],
) -> None:
    svcs = make(40)
    parts = encode_update_parts(NEW, LOCATION, 0, svcs, compact=True)
    full = encode_update_parts(NEW, LOCATION, 30, svcs)
    assert len(parts) <= len(full) and sum(map(len, parts)) < sum(map(len, full))
    if make is noisy_services:
        assert len(parts) > 1  # random text barely deflates: several parts still
    got: list[Service] = []
    for i, data in enumerate(parts):
        assert len(data) <= MAX_ENCODED
        assert len(data) <= MAX_ENCODED
        msg = decode(data)
        assert isinstance(msg, Update) and (msg.part, msg.parts) == (i, len(parts))
        assert msg.location == LOCATION and msg.base is None and msg.origin == NEW
        got.extend(msg.services)
    assert got == svcs


def test_similar_services_deflate_to_a_fraction() -> None:
    """A whole set in compact parts is deflated; a delta against the set it changes."""
    svcs = realistic_services(100)
    parts = encode_update_parts(NEW, LOCATION, 0, svcs, compact=True)
    full = encode_update_parts(NEW, LOCATION, 30, svcs)
    assert 5 * sum(map(len, parts)) < sum(map(len, full))
    assert all(isinstance(m := decode(d), Update) and m.packed is None for d in parts)
    new = Service("svc-100", "Camera 100 (front)", "ros2/topic", "ros2://robot-7/camera_100",
                  {"encoding": "rgb8", "rate": 30, "frame": "cam_100_link"})  # fmt: skip
    delta = Update(NEW, "", 0, 0, 1, (new,), 41, ("svc-003",))
    plain = encode(delta, compact=True)
    packed = encode(delta, compact=True, dictionary=delta_dictionary(svcs))
    assert len(packed) < len(plain) - 100
    got = decode(packed)
    assert isinstance(got, Update) and got.packed is not None and got.services == ()
    assert unpack_delta(got, svcs) == delta  # read against the base set
    wrong = unpack_delta(got, realistic_services(50))  # not the base: garbage, or a reject
    assert wrong != delta
    assert unpack_delta(delta, svcs) is delta  # nothing to unpack
    print(f"100 services: {sum(map(len, full))} bytes in full parts, {sum(map(len, parts))} "
          f"compact; a one-service delta {len(plain)} plain, {len(packed)} deflated")  # fmt: skip


def test_a_packed_body_cannot_inflate_without_bound() -> None:
    bomb = zlib.compressobj(9, zlib.DEFLATED, -15)
    data = PACKED + bomb.compress(b'{"services":[' + b" " * 1_000_000 + b"]}") + bomb.flush()
    head = encode(Update(NEW, LOCATION, 0, 0, 1, ()), compact=True).split(b"\r\n\r\n")[0]
    check_reject(decode(head + b"\r\n\r\n" + data), "bad-body", "more than")
    check_reject(decode(head + b"\r\n\r\n" + PACKED + b"junk"), "bad-body", "deflated")


def test_compact_forms_are_small() -> None:
    """What the compact forms are for: a beacon, a ping, its reply and a one-service delta
    each a fraction of their full forms."""
    beacon = encode(Alive(NEW, "", 0, seq=123456789), compact=True)
    full_beacon = encode(Alive(NEW, LOCATION, 30))
    assert len(beacon) <= 100 < 400 < len(full_beacon)
    ping_msg = Discovery(NEW, "uuid:robot-8", 0, seq=123456789, multicast=False)
    ping = encode(ping_msg, compact=True)
    reply_msg = Response(NEW, "uuid:robot-7", "", 0, seq=123456789)
    reply = encode(reply_msg, compact=True)
    assert 2 * len(ping) < len(encode(ping_msg, group="10.1.0.8", port=1900))
    assert 2 * len(reply) < len(encode(reply_msg))  # the full form's ping reply is compact-ish
    assert len(ping) < 130 and len(reply) < 110
    svc = realistic_services(1)[0]
    delta = Update(NEW, "", 0, 0, 1, (), 41, (svc.id,))
    assert len(encode(delta, compact=True)) < 120
    full_delta = Update(NEW, LOCATION, 30, 0, 1, (), 41, (svc.id,))
    assert len(encode(full_delta)) > 450
    print(f"compact: beacon {len(beacon)}, ping {len(ping)}, reply {len(reply)} bytes")


def test_full_forms_say_the_senders_wire_version() -> None:
    data = encode(Alive(NEW, LOCATION, 30))
    assert b"X-SDFR-WIRE: 2\r\n" in data
    msg = decode(data)
    assert isinstance(msg, Alive) and msg.origin.wire == WIRE_COMPACT
    old = decode(encode(Alive(ORIGIN, LOCATION, 30)))
    assert isinstance(old, Alive) and old.origin.wire == WIRE_FULL
    check_reject(decode(data.replace(b"X-SDFR-WIRE: 2", b"X-SDFR-WIRE: x")), "bad-value", "WIRE")


def test_a_full_search_carries_what_the_fetcher_holds() -> None:
    msg = Discovery(NEW, "uuid:robot-8", 0, want=WANT_ALL, want_version=9, multicast=False, have=7)
    data = encode(msg, group="10.1.0.8", port=1900)
    assert b"X-SDFR-HAVE: 7\r\n" in data and decode(data) == msg
    assert b"X-SDFR-WANT: all\r\nX-SDFR-WANT-VERSION: 9\r\n" in data


def test_what_has_no_compact_form() -> None:
    with pytest.raises(ValueError, match="wire 2"):
        encode(Alive(ORIGIN, "", 0), compact=True)  # a wire-1 origin
    with pytest.raises(ValueError, match="plain SSDP"):
        encode(Discovery(None, "ssdp:all", 2), compact=True)
    with pytest.raises(ValueError, match="unicast"):
        encode(Discovery(NEW, "urn:sdfr-org:fleet:3", 1, multicast=True), compact=True)
    with pytest.raises(ValueError, match="ping reply"):
        encode(Response(NEW, "ssdp:all", LOCATION, 30), compact=True)


def test_a_beacon_says_how_many_turns_its_pinged_robots_take() -> None:
    beacon = Alive(NEW, "", 0, seq=301, turns=4)
    data = encode(beacon, compact=True)
    assert b" 301/4\r\n" in data and decode(data) == beacon
    assert b" 301\r\n" in encode(Alive(NEW, "", 0, seq=301), compact=True)
    for bad in (b" 301/1\r\n", b" 301/0\r\n", b" 301/x\r\n", b" 301/5000\r\n", b" /4\r\n"):
        check_reject(decode(data.replace(b" 301/4\r\n", bad)), "bad-value", "X-SDFR")
    with pytest.raises(ValueError, match="compact"):
        encode(dataclasses.replace(beacon, location=LOCATION, max_age=30))
    with pytest.raises(ValueError, match="seq"):
        encode(dataclasses.replace(beacon, seq=None), compact=True)
    with pytest.raises(ValueError, match="turns"):
        encode(dataclasses.replace(beacon, turns=0), compact=True)


def test_compact_rejects() -> None:
    good = encode(Alive(NEW, "", 0, seq=5), compact=True)
    assert isinstance(decode(good), Alive)
    other = decode(good, fleet=4)
    assert isinstance(other, Reject) and other.reason == "other-fleet"
    line = b"X-SDFR: alive 3 robot-7 1700000000 42 " + b"0" * 16 + b" 5"
    assert line in good
    for bad, reason in (
        (b"X-SDFR: alive 3 robot-7 1700000000 42", "bad-value"),  # a field short
        (line + b" 6", "bad-value"),  # a field too many
        (line.replace(b" 5", b" x"), "bad-value"),  # a seq that is no number
        (b"X-SDFR: update 3 robot-7 1700000000 42 " + b"0" * 16, "bad-value"),  # no PART/base
        (b"X-SDFR: byebye 3 robot-7 1700000000 42 " + b"0" * 16 + b" 5", "bad-value"),
        (b"X-SDFR: response 3 robot-7 1700000000 42 " + b"0" * 16, "bad-value"),  # on a NOTIFY
        (b"X-SDFR: alive 3 robot 7 1700000000 42 " + b"0" * 16, "bad-value"),
        (b"X-SDFR: alive 3 robot-7 1700000000 42 " + b"G" * 16, "bad-value"),
        (b"X-SDFR: alive 3 robot-7 99999999999 42 " + b"0" * 16, "bad-value"),
    ):
        check_reject(decode(good.replace(line, bad)), reason)
    reply = encode(Response(NEW, "uuid:robot-7", "", 0, seq=5), compact=True)
    check_reject(decode(reply.replace(b" 5\r\n", b"\r\n", 1)), "bad-value", "seq")
    svc = Service("a", "a", "t")
    delta = encode(Update(NEW, "", 0, 0, 1, (svc,), 41, ()), compact=True)
    check_reject(decode(delta.replace(b" 41\r\n", b" 42\r\n")), "bad-value", "bases")
    part = encode(Update(NEW, "", 0, 0, 1, (svc,)), compact=True)
    with_base = part.replace(b"0" * 16 + b"\r\n", b"0" * 16 + b" 41\r\n")
    check_reject(decode(with_base), "bad-value", "X-SDFR-PART or a base")


def test_a_compact_fetch_says_what_it_wants_in_one_line() -> None:
    msg = Discovery(NEW, "uuid:robot-8", 0, want=WANT_ALL, want_version=9, multicast=False, have=7)
    data = encode(msg, compact=True)
    assert b"X-SDFR-WANT: all 9 7\r\n" in data and b"HAVE" not in data
    assert decode(data) == msg
    full = encode(msg, group="10.1.0.8", port=1900)
    assert len(full) - len(data) > 200
    ping = Discovery(NEW, "uuid:robot-8", 0, seq=12, multicast=False)
    assert b"X-SDFR-WANT" not in encode(ping, compact=True)
    some = dataclasses.replace(msg, want=(0, 3), want_version=None, have=None)
    assert b"X-SDFR-WANT: 0,3\r\n" in encode(some, compact=True)
    held = dataclasses.replace(msg, want=None, want_version=None)
    assert b"X-SDFR-WANT: - - 7\r\n" in encode(held, compact=True)
    line = b"X-SDFR-WANT: all 9 7"
    for bad in (b"X-SDFR-WANT: all 9 7 1", b"X-SDFR-WANT: all 9 -", b"X-SDFR-WANT: all x 7",
                b"X-SDFR-WANT: none", b"X-SDFR-WANT: "):  # fmt: skip
        check_reject(decode(data.replace(line, bad)), "bad-value", "X-SDFR-WANT")


def _chain_sets(n: int) -> list[tuple[Service, ...]]:
    """`n` versions of a set, each with one service gone and a fresh one added."""
    base = realistic_services(30)
    sets = [tuple(base)]
    for v in range(1, n):
        prev = list(sets[-1])
        prev.pop(v)
        prev.append(dataclasses.replace(base[0], id=f"fresh-{v}", name=f"fresh {v}"))
        sets.append(tuple(prev))
    return sets


def _step(sets: list[tuple[Service, ...]], i: int) -> Update:
    """The delta from version 10 + i (`sets[i]`) to 11 + i, unpacked."""
    old = {s.id: s for s in sets[i]}
    new = sets[i + 1]
    added = tuple(s for s in new if old.get(s.id) != s)
    removed = tuple(sid for sid in old if sid not in {s.id for s in new})
    origin = dataclasses.replace(NEW, version=11 + i)
    return Update(origin, "", 0, 0, 1, added, 10 + i, removed)


def _apply(have: tuple[Service, ...], read: object) -> tuple[Service, ...]:
    assert isinstance(read, tuple), read
    changed = {s.id: s for s in read[0]}
    kept = tuple(changed.pop(s.id, s) for s in have if s.id not in read[1])
    return kept + tuple(changed.values())


def test_a_delta_carries_the_steps_before_it_and_each_reads_from_its_own_base() -> None:
    sets = _chain_sets(4)
    steps = []
    for i in range(2):
        data = encode(_step(sets, i), compact=True, dictionary=delta_dictionary(sets[i]))
        steps.append((10 + i, last_step(data)))
        assert data.endswith(steps[-1][1]) and steps[-1][1].startswith(PACKED)
    own = dataclasses.replace(_step(sets, 2), steps=tuple(steps))
    data = encode(own, compact=True, dictionary=delta_dictionary(sets[2]))
    n0, n1 = len(steps[0][1]), len(steps[1][1])
    assert f" 10/{n0},11/{n1},12\r\n".encode() in data
    got = decode(data)
    assert isinstance(got, Update) and got.steps == tuple(steps) and got.base == 12
    assert data.endswith(last_step(data)) and len(last_step(data)) < len(data) - n0 - n1
    # From the oldest base, step by step, to the newest set.
    have = sets[0]
    for base, body in got.steps:
        have = _apply(have, read_step(body, have))
        assert have == sets[base - 9]
    final = unpack_delta(got, have)
    assert isinstance(final, Update)
    assert _apply(have, (final.services, final.removed)) == sets[3]
    # A step read against a set that is not its base: a reject, or garbage the digest catches.
    wrong = read_step(steps[1][1], sets[0])
    assert isinstance(wrong, Reject) or wrong != read_step(steps[1][1], sets[1])


def test_a_delta_chain_that_does_not_add_up_is_refused() -> None:
    sets = _chain_sets(3)
    first = encode(_step(sets, 0), compact=True, dictionary=delta_dictionary(sets[0]))
    body = last_step(first)
    own = dataclasses.replace(_step(sets, 1), steps=((10, body),))
    data = encode(own, compact=True, dictionary=delta_dictionary(sets[1]))
    n = len(body)
    field = f" 10/{n},11\r\n"
    assert field.encode() in data
    for bad, detail in (
        (f" 10/{len(data)},11\r\n", "length"),  # longer than the body
        (" 10/0,11\r\n", "length"),
        (f" 11/{n},11\r\n", "bases"),  # not rising
        (f" 10/{n},12\r\n", "bases"),  # the last base is not below the version
        (" 10,11\r\n", "<base>/<length>"),
        (f" 6/1,7/1,8/1,10/{n},11\r\n", "steps"),  # more than MAX_STEPS
    ):
        check_reject(decode(data.replace(field.encode(), bad.encode())), "bad-value", detail)
    for wrong in (((11, body),), ((10, b""),), tuple((i, body) for i in range(4, 8))):
        with pytest.raises(ValueError):
            encode(dataclasses.replace(own, steps=wrong), compact=True)
    with pytest.raises(ValueError, match="compact"):
        encode(dataclasses.replace(own, location=LOCATION, max_age=30))
