"""The wire codec: round trips, standard SSDP interop, rejects, and a decoder that never raises."""

from __future__ import annotations

import io
import itertools
import json
import time
from http.client import parse_headers

import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from sdfr import __version__
from sdfr.errors import ValidationError
from sdfr.records.model import Service
from sdfr.wire import (
    DEFAULT_GROUP,
    DEVICE_TYPE,
    MAX_DATAGRAM,
    MAX_ENCODED,
    MAX_HOST,
    MAX_LOCATION,
    SEAL_RESERVE,
    SERVER,
    WIRE_COMPACT,
    Alive,
    Byebye,
    Discovery,
    Message,
    Origin,
    Reject,
    Response,
    Update,
    Want,
    check_service_fits,
    decode,
    encode,
    encode_update_parts,
    fleet_target,
    max_service_json_bytes,
)
from tests.support.wire_data import (
    ASYNC_UPNP_CLIENT_SEARCH,
    LOCATION,
    ORIGIN,
    check_reject,
    corpus,
    edit,
    header_texts,
    headers_of,
    locations,
    max_ages,
    origins,
    realistic_services,
    seqs,
    service_lists,
    services,
    wants,
)

# --------------------------------------------------------------------------------------------
# Round trips


@given(
    origin=st.none() | origins,
    st_=header_texts,
    mx=st.integers(0, 5),
    seq=seqs,
    want=wants,
    want_version=st.none() | st.integers(0, 2**53),
    multicast=st.booleans(),
)
def test_discovery_round_trip(
    origin: Origin | None,
    st_: str,
    mx: int,
    seq: int | None,
    want: Want,
    want_version: int | None,
    multicast: bool,
) -> None:
    if origin is None:
        seq = want = want_version = None
    msg = Discovery(origin, st_, mx, seq, want, want_version, multicast)
    group = DEFAULT_GROUP if multicast else "192.0.2.7"
    data = encode(msg, group=group, port=1900)
    assert len(data) <= MAX_DATAGRAM
    assert decode(data) == msg
    if origin is not None:
        assert decode(data, fleet=origin.fleet) == msg


@given(origin=origins, st_=header_texts, location=locations, max_age=max_ages, seq=seqs)
def test_response_round_trip(
    origin: Origin, st_: str, location: str, max_age: int, seq: int | None
) -> None:
    msg = Response(origin, st_, location, max_age, seq)
    assert decode(encode(msg)) == msg


@given(origin=origins, st_=header_texts, seq=st.integers(0, 2**53), ping=seqs)
def test_compact_ping_reply_round_trip(
    origin: Origin, st_: str, seq: int, ping: int | None
) -> None:
    msg = Response(origin, st_, "", 0, seq, ping)
    data = encode(msg)
    assert decode(data) == msg
    full = encode(Response(origin, st_, LOCATION, 1800, seq, ping))
    assert decode(full) == Response(origin, st_, LOCATION, 1800, seq, ping)
    assert len(full) - len(data) >= 100 + len(LOCATION)


def test_only_a_ping_reply_carries_a_ping() -> None:
    with pytest.raises(ValueError, match="only a ping reply"):
        encode(Response(ORIGIN, "ssdp:all", LOCATION, 1800, ping=3))
    data = encode(Response(ORIGIN, "uuid:robot-7", LOCATION, 1800, seq=5, ping=3))
    assert b"X-SDFR-PING: 3\r\n" in data
    check_reject(decode(data.replace(b"X-SDFR-SEQ: 5\r\n", b"")), "bad-value", "X-SDFR-PING")


def test_a_compact_reply_is_only_for_pings() -> None:
    data = encode(Response(ORIGIN, "uuid:robot-7", "", 0, seq=5))
    head = data.decode()
    for name in ("CACHE-CONTROL", "EXT:", "LOCATION", "SERVER", "USN"):
        assert name not in head, name
    assert "X-SDFR-SEQ: 5" in head and "X-SDFR-ROBOT: robot-7" in head
    with pytest.raises(ValueError, match="LOCATION"):
        encode(Response(ORIGIN, "ssdp:all", "", 0))  # a search response needs its LOCATION
    with pytest.raises(ValueError, match="max_age 0"):
        encode(Response(ORIGIN, "ssdp:all", "", 1800, seq=5))
    # Without SEQ, a response lacking LOCATION is refused as before.
    check_reject(decode(data.replace(b"X-SDFR-SEQ: 5\r\n", b"")), "missing-header", "LOCATION")


@given(origin=origins, location=locations, max_age=max_ages)
def test_alive_and_byebye_round_trip(origin: Origin, location: str, max_age: int) -> None:
    alive = Alive(origin, location, max_age)
    assert decode(encode(alive)) == alive
    bye = Byebye(origin)
    assert decode(encode(bye)) == bye


@given(
    origin=origins,
    location=locations,
    max_age=max_ages,
    svcs=st.lists(services, max_size=3, unique_by=lambda s: s.id),
    shape=st.integers(1, 255).flatmap(lambda n: st.tuples(st.integers(0, n - 1), st.just(n))),
)
def test_update_round_trip(
    origin: Origin,
    location: str,
    max_age: int,
    svcs: list[Service],
    shape: tuple[int, int],
) -> None:
    part, parts = shape
    msg = Update(origin, location, max_age, part, parts, tuple(svcs))
    try:
        data = encode(msg)
    except ValueError:
        assume(False)
    assert len(data) <= MAX_DATAGRAM
    assert decode(data) == msg


def test_update_with_unicode_round_trips() -> None:
    svc = Service(
        id="cam.0",
        name="Kamera vorne \u2013 \u00fcberall \U0001f916",
        type="ros2/topic",
        url="http://\u00e9xample/\u6444\u50cf",
        attributes={"\u6807\u7b7e": "\u503c", "emoji": "\U0001f680", "n": -3, "x": 0.5},
    )
    msg = Update(ORIGIN, LOCATION, 60, 0, 1, (svc,))
    data = encode(msg)
    assert "\U0001f916".encode() in data  # ensure_ascii=False: raw UTF-8 in the body
    assert decode(data) == msg


def test_plain_discovery_has_only_standard_headers() -> None:
    data = encode(Discovery(None, "ssdp:all", 3))
    assert data == (
        b"M-SEARCH * HTTP/1.1\r\nHOST: 239.255.255.250:1900\r\n"
        b'MAN: "ssdp:discover"\r\nMX: 3\r\nST: ssdp:all\r\n\r\n'
    )


def test_every_sdfr_message_carries_the_common_headers() -> None:
    for data in corpus()[1:]:
        headers = headers_of(data)
        for name in (
            "X-SDFR-FLEET",
            "X-SDFR-ROBOT",
            "X-SDFR-TYPE",
            "X-SDFR-VERSION",
            "X-SDFR-DIGEST",
            "BOOTID.UPNP.ORG",
            "CONFIGID.UPNP.ORG",
        ):
            assert name in headers, (name, data)


def test_configid_is_version_modulo_2_24() -> None:
    origin = Origin(1, "r1", 0, 2**24 + 5, "a" * 16)
    data = encode(Alive(origin, LOCATION, 30))
    assert headers_of(data)["CONFIGID.UPNP.ORG"] == "5"
    assert headers_of(data)["X-SDFR-VERSION"] == str(2**24 + 5)
    assert decode(data) == Alive(origin, LOCATION, 30)


def test_notify_headers() -> None:
    svcs = realistic_services(2)
    data = encode(Update(ORIGIN, LOCATION, 1800, 0, 1, tuple(svcs)))
    headers = headers_of(data)
    assert data.startswith(b"NOTIFY * HTTP/1.1\r\n")
    assert headers["HOST"] == "239.255.255.250:1900"
    assert headers["NT"] == "urn:sdfr-org:fleet:3"
    assert headers["NTS"] == "ssdp:update"
    assert headers["USN"] == "uuid:robot-7::urn:sdfr-org:device:robot:1"
    assert headers["CACHE-CONTROL"] == "max-age=1800"
    assert headers["X-SDFR-PART"] == "1/1"
    assert headers["CONTENT-TYPE"] == "application/json"
    body = data.partition(b"\r\n\r\n")[2]
    assert int(headers["CONTENT-LENGTH"]) == len(body)
    assert json.loads(body) == {"services": [s.to_json() for s in svcs]}
    assert b" " not in body.replace(b"Camera ", b"").replace(b" (front)", b"")  # compact
    bye = headers_of(encode(Byebye(ORIGIN)))
    assert bye["NTS"] == "ssdp:byebye" and "LOCATION" not in bye
    assert headers_of(encode(Alive(ORIGIN, LOCATION, 5)))["NTS"] == "ssdp:alive"


def test_unicast_discovery() -> None:
    msg = Discovery(ORIGIN, fleet_target(3), 0, seq=1, multicast=False)
    data = encode(msg, group="10.0.0.9", port=1900)
    headers = headers_of(data)
    assert headers["HOST"] == "10.0.0.9:1900"
    assert "MX" not in headers  # unicast searches need no MX
    assert decode(data) == msg
    v6 = encode(Discovery(None, "ssdp:all", 2, multicast=False), group="fe80::1", port=1900)
    assert headers_of(v6)["HOST"] == "[fe80::1]:1900"
    assert decode(v6) == Discovery(None, "ssdp:all", 2, multicast=False)
    assert decode(encode(Discovery(None, "ssdp:all", 2), group="ff02::c")) == Discovery(
        None, "ssdp:all", 2
    )


def test_decode_multicast_flag_with_group() -> None:
    data = encode(Discovery(None, "ssdp:all", 2), group="239.1.2.3")
    assert decode(data).multicast is True  # type: ignore[union-attr]
    assert decode(data, group="239.1.2.3").multicast is True  # type: ignore[union-attr]
    assert decode(data, group=DEFAULT_GROUP).multicast is False  # type: ignore[union-attr]
    no_man = decode(edit(data, drop=("MAN",)))
    assert isinstance(no_man, Discovery) and no_man.multicast is False


# --------------------------------------------------------------------------------------------
# Encoding errors


@pytest.mark.parametrize(
    "msg",
    [
        Alive(Origin(256, "r", 0, 0, "0" * 16), LOCATION, 5),
        Alive(Origin(1, "-r", 0, 0, "0" * 16), LOCATION, 5),
        Alive(Origin(1, "r\n", 0, 0, "0" * 16), LOCATION, 5),
        Alive(Origin(1, "r", 2**31, 0, "0" * 16), LOCATION, 5),
        Alive(Origin(1, "r", 0, 2**53 + 1, "0" * 16), LOCATION, 5),
        Alive(Origin(1, "r", 0, 0, "0" * 15), LOCATION, 5),
        Alive(Origin(1, "r", 0, 0, "A" * 16), LOCATION, 5),
        Alive(ORIGIN, LOCATION, 0),
        Alive(ORIGIN, "http://x/\r\nX-EVIL: 1", 5),
        Alive(ORIGIN, " http://x/", 5),
        Alive(ORIGIN, "", 5),
        Alive(ORIGIN, "http://x/" + "a" * MAX_LOCATION, 5),
        Response(ORIGIN, "ssdp:all\r\nX: y", LOCATION, 5),
        Response(ORIGIN, "ssdp:all", LOCATION, 5, seq=-1),
        Discovery(ORIGIN, "ssdp:all", 6),
        Discovery(ORIGIN, "ssdp:all", 2, want=(3, 1)),
        Discovery(ORIGIN, "ssdp:all", 2, want=(1, 1)),
        Discovery(ORIGIN, "ssdp:all", 2, want=(256,)),
        Discovery(ORIGIN, "ssdp:all", 2, want=()),
        Discovery(None, "ssdp:all", 2, seq=1),
        Discovery(ORIGIN, "x" * MAX_DATAGRAM, 2),
        Discovery(ORIGIN, "ssdp:all", 2, multicast=False),  # HOST would be the group
        Update(ORIGIN, LOCATION, 5, 1, 1, ()),
        Update(ORIGIN, LOCATION, 5, 0, 256, ()),
        Update(ORIGIN, LOCATION, 5, 0, 1, (Service("a", "A", "t"), Service("a", "B", "t"))),
        Update(ORIGIN, LOCATION, 5, 0, 1, (Service("a", "A", "t", None, {"x": float("inf")}),)),
        Update(ORIGIN, LOCATION, 5, 0, 1, (Service("a", "\ud800", "t"),)),
    ],
)
def test_encode_rejects_bad_messages(msg: Message) -> None:
    with pytest.raises(ValueError):
        encode(msg)


def test_multicast_discovery_needs_a_multicast_group() -> None:
    with pytest.raises(ValueError, match="multicast"):
        encode(Discovery(None, "ssdp:all", 2), group="10.0.0.1")


# --------------------------------------------------------------------------------------------
# Update parts


@given(origin=origins, location=locations, max_age=max_ages, svcs=service_lists)
def test_update_parts_reassemble(
    origin: Origin, location: str, max_age: int, svcs: list[Service]
) -> None:
    datagrams = encode_update_parts(origin, location, max_age, svcs)
    decoded = [decode(d) for d in datagrams]
    assert all(len(d) <= MAX_DATAGRAM for d in datagrams)
    assert all(isinstance(u, Update) for u in decoded)
    updates = [u for u in decoded if isinstance(u, Update)]
    assert [u.part for u in updates] == list(range(len(datagrams)))
    assert {u.parts for u in updates} == {len(datagrams)}
    assert all((u.origin, u.location, u.max_age) == (origin, location, max_age) for u in updates)
    assert [s for u in updates for s in u.services] == svcs
    # Greedy: the first service of each part would not have fitted in the part before.
    for before, after in itertools.pairwise(updates):
        grown = Update(
            origin,
            location,
            max_age,
            before.part,
            before.parts,
            (*before.services, after.services[0]),
        )
        with pytest.raises(ValueError):
            encode(grown)


def test_update_parts_of_100_services() -> None:
    svcs = realistic_services(100)
    sizes = [len(json.dumps(s.to_json(), separators=(",", ":"))) for s in svcs]
    assert min(sizes) >= 130 and max(sizes) <= 180
    datagrams = encode_update_parts(ORIGIN, LOCATION, 1800, svcs)
    assert 8 <= len(datagrams) <= 25
    # Each leaves room for a seal (sdfr.protocol.auth), so a keyed fleet has the same limits.
    assert all(len(d) <= MAX_ENCODED == MAX_DATAGRAM - SEAL_RESERVE for d in datagrams)
    updates = [decode(d) for d in datagrams]
    assert [s for u in updates for s in u.services] == svcs  # type: ignore[union-attr]
    assert {u.parts for u in updates} == {len(datagrams)}  # type: ignore[union-attr]
    # Most parts are nearly full.
    assert sum(len(d) for d in datagrams) > 0.85 * MAX_ENCODED * len(datagrams)


def test_update_parts_are_fast() -> None:
    svcs = realistic_services(100)
    best = float("inf")
    for _ in range(5):
        t0 = time.perf_counter()
        encode_update_parts(ORIGIN, LOCATION, 1800, svcs)
        best = min(best, time.perf_counter() - t0)
    assert best < 0.02  # about 0.3 ms on a laptop; this only catches quadratic blowups


def test_update_parts_with_more_than_nine_parts_number_correctly() -> None:
    svcs = realistic_services(200)
    datagrams = encode_update_parts(ORIGIN, LOCATION, 1800, svcs)
    assert len(datagrams) >= 10
    assert headers_of(datagrams[0])["X-SDFR-PART"] == f"1/{len(datagrams)}"
    assert headers_of(datagrams[-1])["X-SDFR-PART"] == f"{len(datagrams)}/{len(datagrams)}"


def test_empty_service_set_is_one_empty_part() -> None:
    (data,) = encode_update_parts(ORIGIN, LOCATION, 1800, [])
    assert decode(data) == Update(ORIGIN, LOCATION, 1800, 0, 1, ())
    assert data.endswith(b'\r\n\r\n{"services":[]}')


def test_oversized_service_raises() -> None:
    big = Service("huge", "x" * 128, "t", "u" * 256, {f"k{i}": "v" * 200 for i in range(8)})
    with pytest.raises(ValueError, match="huge"):
        encode_update_parts(ORIGIN, LOCATION, 1800, [*realistic_services(3), big])
    with pytest.raises(ValidationError) as info:
        check_service_fits(big)
    assert info.value.field == "service"
    assert str(max_service_json_bytes()) in str(info.value)


def test_update_parts_reject_duplicate_ids_and_bad_values() -> None:
    with pytest.raises(ValueError, match="duplicate"):
        encode_update_parts(ORIGIN, LOCATION, 1800, [Service("a", "A", "t")] * 2)
    with pytest.raises(ValueError):
        encode_update_parts(ORIGIN, LOCATION, 1800, [Service("a", "A", "t", None, {"x": 1e999})])
    with pytest.raises(ValidationError):
        check_service_fits(Service("a", "A", "t", None, {"x": float("nan")}))


def test_check_service_fits_accepts_normal_services() -> None:
    for svc in realistic_services(3):
        check_service_fits(svc)


def service_of_json_size(size: int) -> Service:
    svc = Service("s", "", "t")
    base = len(json.dumps(svc.to_json(), separators=(",", ":")))
    return Service("s", "n" * (size - base), "t")


def test_max_service_json_bytes_is_tight() -> None:
    """A service of exactly the limit fits with the longest possible headers, one more does not."""
    limit = max_service_json_bytes()
    assert 450 < limit < MAX_ENCODED
    worst = Origin(255, "r" * 64, 2**31 - 1, 2**53 - 1, "f" * 16, WIRE_COMPACT)
    location = "l" * MAX_LOCATION
    group = "ffff:ffff:ffff:ffff:ffff:ffff:ffff:ffff"
    assert len(f"[{group}]:65535") == MAX_HOST
    fits = service_of_json_size(limit)
    check_service_fits(fits)
    data = encode(Update(worst, location, 86400, 254, 255, (fits,)), group=group, port=65535)
    assert len(data) == MAX_ENCODED
    too_big = service_of_json_size(limit + 1)
    with pytest.raises(ValidationError):
        check_service_fits(too_big)
    with pytest.raises(ValueError):
        encode(Update(worst, location, 86400, 254, 255, (too_big,)), group=group, port=65535)
    # With ordinary headers the limit service of course still goes out.
    assert len(encode_update_parts(ORIGIN, LOCATION, 60, [fits])) == 1


# --------------------------------------------------------------------------------------------
# Standard SSDP interop

GSSDP_SEARCH = (
    b"M-SEARCH * HTTP/1.1\r\n"
    b"Host: 239.255.255.250:1900\r\n"
    b'Man: "ssdp:discover"\r\n'
    b"ST: urn:schemas-upnp-org:device:MediaServer:1\r\n"
    b"MX: 3\r\n"
    b"User-Agent: Linux/6.1 UPnP/1.0 GUPnP/1.6.6 DLNADOC/1.50\r\n"
    b"\r\n"
)
ROUTER_NOTIFY = (
    b"NOTIFY * HTTP/1.1\r\n"
    b"HOST: 239.255.255.250:1900\r\n"
    b"CACHE-CONTROL: max-age=120\r\n"
    b"LOCATION: http://192.168.1.1:5000/rootDesc.xml\r\n"
    b"SERVER: OpenWRT/23.05 UPnP/1.1 MiniUPnPd/2.3.3\r\n"
    b"NT: upnp:rootdevice\r\n"
    b"USN: uuid:4f3e1a52-6b5c-4a1e-9a0e-1c2d3e4f5a6b::upnp:rootdevice\r\n"
    b"NTS: ssdp:alive\r\n"
    b'OPT: "http://schemas.upnp.org/upnp/1/0/"; ns=01\r\n'
    b"01-NLS: 1700000000\r\n"
    b"BOOTID.UPNP.ORG: 1700000000\r\n"
    b"CONFIGID.UPNP.ORG: 1337\r\n"
    b"\r\n"
)
ROUTER_RESPONSE = (
    b"HTTP/1.1 200 OK\r\n"
    b"CACHE-CONTROL: max-age=120\r\n"
    b"ST: upnp:rootdevice\r\n"
    b"USN: uuid:4f3e1a52-6b5c-4a1e-9a0e-1c2d3e4f5a6b::upnp:rootdevice\r\n"
    b"EXT:\r\n"
    b"SERVER: OpenWRT/23.05 UPnP/1.1 MiniUPnPd/2.3.3\r\n"
    b"LOCATION: http://192.168.1.1:5000/rootDesc.xml\r\n"
    b"\r\n"
)


def test_standard_client_search_decodes_as_plain_discovery() -> None:
    assert decode(ASYNC_UPNP_CLIENT_SEARCH) == Discovery(origin=None, st="ssdp:all", mx=4)
    assert decode(ASYNC_UPNP_CLIENT_SEARCH, fleet=3) == Discovery(None, "ssdp:all", 4)
    assert decode(GSSDP_SEARCH) == Discovery(None, "urn:schemas-upnp-org:device:MediaServer:1", 3)
    compact = ASYNC_UPNP_CLIENT_SEARCH.replace(b": ", b":")  # no space after the colon
    assert decode(compact) == Discovery(None, "ssdp:all", 4)
    unquoted = ASYNC_UPNP_CLIENT_SEARCH.replace(b'"ssdp:discover"', b"ssdp:discover")
    assert decode(unquoted) == Discovery(None, "ssdp:all", 4)


def test_plain_upnp_devices_are_not_sdfr() -> None:
    check_reject(decode(ROUTER_NOTIFY), "not-sdfr")
    check_reject(decode(ROUTER_NOTIFY, fleet=3), "not-sdfr")
    check_reject(decode(ROUTER_RESPONSE), "not-sdfr")


def test_response_is_a_standard_ssdp_search_response() -> None:
    data = encode(Response(ORIGIN, "ssdp:all", LOCATION, 1800, seq=5))
    status, _, rest = data.partition(b"\r\n")
    assert status == b"HTTP/1.1 200 OK"
    msg = parse_headers(io.BytesIO(rest))
    for name in ("CACHE-CONTROL", "EXT", "LOCATION", "SERVER", "ST", "USN"):
        assert msg[name] is not None, name
    assert msg["EXT"] == ""
    assert msg["CACHE-CONTROL"] == "max-age=1800"
    assert msg["LOCATION"] == LOCATION
    assert msg["ST"] == "ssdp:all"
    assert msg["USN"] == f"uuid:robot-7::{DEVICE_TYPE}"
    assert msg["SERVER"] == SERVER == f"Linux UPnP/1.1 SDfR/{__version__}"
    assert msg["BOOTID.UPNP.ORG"] == str(ORIGIN.boot_id)
    assert data.endswith(b"\r\n\r\n") and data.count(b"\r\n\r\n") == 1


def test_other_fleet_is_filtered() -> None:
    for data in corpus()[1:]:
        check_reject(decode(data, fleet=4), "other-fleet", "3")
        assert not isinstance(decode(data, fleet=3), Reject)
        lower = data.replace(b"X-SDFR-FLEET:", b"x-sdfr-fleet:")
        check_reject(decode(lower, fleet=4), "other-fleet")
        # The fleet filter goes first: even an otherwise broken datagram is just other-fleet.
        broken = data.replace(b"X-SDFR-DIGEST", b"X-SDFR-DIGESTX")
        check_reject(decode(broken, fleet=4), "other-fleet")


def test_headers_are_case_insensitive() -> None:
    for data in corpus():
        head, sep, body = data.partition(b"\r\n\r\n")
        lines = head.split(b"\r\n")
        lower = [lines[0]] + [
            n.lower() + b":" + v for n, _, v in (line.partition(b":") for line in lines[1:])
        ]
        assert decode(b"\r\n".join(lower) + sep + body) == decode(data)
        assert not isinstance(decode(data), Reject)


def test_bare_newline_line_endings() -> None:
    for data in corpus():
        assert decode(data.replace(b"\r\n", b"\n")) == decode(data)
    assert decode(ASYNC_UPNP_CLIENT_SEARCH.replace(b"\r\n", b"\n")) == Discovery(
        None, "ssdp:all", 4
    )


def test_missing_final_blank_line_is_tolerated_for_headers_only() -> None:
    assert decode(ASYNC_UPNP_CLIENT_SEARCH[:-2]) == Discovery(None, "ssdp:all", 4)
    assert decode(ASYNC_UPNP_CLIENT_SEARCH[:-4]) == Discovery(None, "ssdp:all", 4)


def test_mx_rules() -> None:
    def mx_of(data: bytes) -> int:
        result = decode(data)
        assert isinstance(result, Discovery), result
        return result.mx

    assert mx_of(edit(ASYNC_UPNP_CLIENT_SEARCH, MX="120")) == 5
    assert mx_of(edit(ASYNC_UPNP_CLIENT_SEARCH, MX="0")) == 0
    assert mx_of(edit(ASYNC_UPNP_CLIENT_SEARCH, drop=("MX",))) == 0
    check_reject(decode(edit(ASYNC_UPNP_CLIENT_SEARCH, MX="121")), "bad-value", "MX")
    check_reject(decode(edit(ASYNC_UPNP_CLIENT_SEARCH, MX="-1")), "bad-value", "MX")
    check_reject(decode(edit(ASYNC_UPNP_CLIENT_SEARCH, MX="three")), "bad-value", "MX")


def test_want_is_normalised() -> None:
    data = edit(corpus()[1], X_SDFR_WANT="4, 0,3,3")
    result = decode(data)
    assert isinstance(result, Discovery) and result.want == (0, 3, 4)
    every = Discovery(ORIGIN, "ssdp:all", 1, want=tuple(range(256)))
    assert decode(encode(every)) == every
