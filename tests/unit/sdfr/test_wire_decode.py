"""The decoder on what a robot must refuse: each reject with its reason, and no input that
makes it raise."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from sdfr.records.model import Service, service_digest
from sdfr.wire import (
    MAX_DATAGRAM,
    MAX_LOCATION,
    Alive,
    Discovery,
    Origin,
    Reject,
    Response,
    Update,
    decode,
    encode,
    encode_update_parts,
)
from tests.support.wire_data import (
    ASYNC_UPNP_CLIENT_SEARCH,
    LOCATION,
    ORIGIN,
    check_decoded,
    check_reject,
    corpus,
    edit,
    headers_of,
    realistic_services,
)

# --------------------------------------------------------------------------------------------
# Rejects

ALIVE = encode(Alive(ORIGIN, LOCATION, 1800))
UPDATE = encode(Update(ORIGIN, LOCATION, 1800, 0, 2, tuple(realistic_services(2))))
SEARCH = encode(Discovery(ORIGIN, "ssdp:all", 2, seq=1))
RESPONSE = encode(Response(ORIGIN, "ssdp:all", LOCATION, 1800, seq=1))


def with_body(body: bytes) -> bytes:
    head = UPDATE.partition(b"\r\n\r\n")[0]
    return edit(head + b"\r\n\r\n", CONTENT_LENGTH=str(len(body))) + body


@pytest.mark.parametrize(
    ("data", "reason", "detail"),
    [
        (ALIVE + b" " * (MAX_DATAGRAM + 1 - len(ALIVE)), "too-large", "1401"),
        (b"", "bad-start-line", ""),
        (b"\x00\xff\xfe garbage", "bad-start-line", ""),
        (b"GET / HTTP/1.1\r\nHost: x\r\n\r\n", "bad-start-line", "GET"),
        (b"GET / HTTP/1.1\r\nnot a header\r\n\r\n", "bad-start-line", "GET"),
        (b"HTTP/1.1 404 Not Found\r\nnot a header\r\n\r\n", "unsupported", "404"),
        (b"M-SEARCH * HTTP/1.0\r\nST: x\r\n\r\n", "bad-start-line", ""),
        (b"HTTP/1.1 2000 OK\r\n\r\n", "bad-start-line", ""),
        (b"HTTP/1.1 20\r\n\r\n", "bad-start-line", ""),
        (b"HTTP/1.1 \r\n\r\n", "bad-start-line", ""),
        (b"HTTP/1.1 200\r\nST: x\r\n\r\n", "not-sdfr", ""),
        (b"HTTP/1.1 404 Not Found\r\n\r\n", "unsupported", "404"),
        (edit(ALIVE, NTS="ssdp:propchange"), "unsupported", "propchange"),
        (ALIVE.replace(b"NT: ", b"NT "), "bad-header", "NT"),
        (ALIVE.replace(b"\r\n\r\n", b"\r\n: empty name\r\n\r\n"), "bad-header", ""),
        (ALIVE.replace(b"\r\n\r\n", b"\r\nX-SDFR-FLEET: 9\r\n\r\n"), "bad-header", "twice"),
        (edit(ALIVE, drop=("BOOTID.UPNP.ORG",)), "missing-header", "BOOTID.UPNP.ORG"),
        (edit(ALIVE, drop=("X-SDFR-DIGEST",)), "missing-header", "X-SDFR-DIGEST"),
        (edit(ALIVE, drop=("LOCATION",)), "missing-header", "LOCATION"),
        (edit(ALIVE, drop=("CACHE-CONTROL",)), "missing-header", "CACHE-CONTROL"),
        (edit(ALIVE, drop=("NTS",)), "missing-header", "NTS"),
        (edit(ALIVE, drop=("NT",)), "missing-header", "NT"),
        (edit(UPDATE, drop=("X-SDFR-PART",)), "missing-header", "X-SDFR-PART"),
        (edit(SEARCH, drop=("ST",)), "missing-header", "ST"),
        (edit(ASYNC_UPNP_CLIENT_SEARCH, drop=("ST",)), "missing-header", "ST"),
        (edit(RESPONSE, drop=("ST",)), "missing-header", "ST"),
        (edit(ALIVE, X_SDFR_FLEET="256"), "bad-value", "X-SDFR-FLEET"),
        (edit(ALIVE, X_SDFR_FLEET="x"), "bad-value", "X-SDFR-FLEET"),
        (edit(ALIVE, X_SDFR_ROBOT="-bad"), "bad-value", "X-SDFR-ROBOT"),
        (edit(ALIVE, X_SDFR_DIGEST="0123456789ABCDEF"), "bad-value", "X-SDFR-DIGEST"),
        (edit(ALIVE, X_SDFR_VERSION="1e3"), "bad-value", "X-SDFR-VERSION"),
        (edit(ALIVE, X_SDFR_VERSION=str(2**53 + 1)), "bad-value", "X-SDFR-VERSION"),
        (edit(ALIVE, X_SDFR_VERSION="\u0661"), "bad-value", "X-SDFR-VERSION"),  # Arabic 1
        (edit(ALIVE, X_SDFR_TYPE="update"), "bad-value", "X-SDFR-TYPE"),
        (edit(SEARCH, X_SDFR_TYPE="response"), "bad-value", "X-SDFR-TYPE"),
        (edit(RESPONSE, X_SDFR_TYPE="alive"), "bad-value", "X-SDFR-TYPE"),
        (edit(ALIVE, BOOTID__UPNP__ORG=str(2**31)), "bad-value", "BOOTID"),
        (edit(ALIVE, CONFIGID__UPNP__ORG="7"), "bad-value", "CONFIGID"),
        (edit(ALIVE, NT="upnp:rootdevice"), "bad-value", "NT"),
        (edit(ALIVE, USN="uuid:someone-else::x"), "bad-value", "USN"),
        (edit(ALIVE, CACHE_CONTROL="no-cache"), "bad-value", "CACHE-CONTROL"),
        (edit(ALIVE, CACHE_CONTROL="max-age=0"), "bad-value", "CACHE-CONTROL"),
        (edit(ALIVE, LOCATION="x" * (MAX_LOCATION + 1)), "bad-value", "LOCATION"),
        (edit(SEARCH, MAN="ssdp:alive"), "bad-value", "MAN"),
        (edit(SEARCH, ST=""), "bad-value", "ST"),
        (edit(SEARCH, X_SDFR_SEQ="-1"), "bad-value", "X-SDFR-SEQ"),
        (edit(SEARCH, X_SDFR_WANT="1,x"), "bad-value", "X-SDFR-WANT"),
        (edit(SEARCH, X_SDFR_WANT="256"), "bad-value", "X-SDFR-WANT"),
        (edit(SEARCH, X_SDFR_WANT=""), "bad-value", "X-SDFR-WANT"),
        (edit(SEARCH, X_SDFR_WANT_VERSION="v1"), "bad-value", "X-SDFR-WANT-VERSION"),
        (edit(UPDATE, X_SDFR_PART="0/2"), "bad-value", "X-SDFR-PART"),
        (edit(UPDATE, X_SDFR_PART="3/2"), "bad-value", "X-SDFR-PART"),
        (edit(UPDATE, X_SDFR_PART="1/256"), "bad-value", "X-SDFR-PART"),
        (edit(UPDATE, X_SDFR_PART="1"), "bad-value", "X-SDFR-PART"),
        (edit(UPDATE, CONTENT_LENGTH="abc"), "bad-value", "CONTENT-LENGTH"),
        (UPDATE[:-1], "bad-body", "CONTENT-LENGTH"),
        (UPDATE + b"\r\n", "bad-body", "CONTENT-LENGTH"),
        (with_body(b""), "bad-body", "JSON"),
        (with_body(b"{"), "bad-body", "JSON"),
        (with_body(b"[]"), "bad-body", "object"),
        (with_body(b'{"services":{}}'), "bad-body", "list"),
        (with_body(b'{"services":[1]}'), "bad-body", "services[0]"),
        (with_body(b'{"services":[{"id":"a","name":"A"}]}'), "bad-body", "type"),
        (
            with_body(b'{"services":[{"id":"a","name":"A","type":"t","colour":"red"}]}'),
            "bad-body",
            "colour",
        ),
        (
            with_body(
                b'{"services":[{"id":"a","name":"A","type":"t"},{"id":"a","name":"B","type":"t"}]}'
            ),
            "bad-body",
            "duplicate",
        ),
        (
            with_body(b'{"services":[{"id":"a","name":"A","type":"t","attributes":{"x":NaN}}]}'),
            "bad-body",
            "NaN",
        ),
        (with_body(b"[" * 850), "bad-body", "JSON"),  # deep nesting, within the size limit
        (with_body(b"[" * 400 + b"]" * 400), "bad-body", "object"),
        (with_body(b'{"services":[{"id":"a","name":"\xff","type":"t"}]}'), "bad-body", ""),
    ],
)
def test_decode_rejects(data: bytes, reason: str, detail: str) -> None:
    check_reject(decode(data), reason, detail)


def test_update_without_content_length_takes_the_rest() -> None:
    data = edit(UPDATE, drop=("CONTENT-LENGTH",))
    result = decode(data)
    assert isinstance(result, Update) and len(result.services) == 2


def test_digest_matches_model_fingerprint() -> None:
    svcs = realistic_services(4)
    origin = Origin(1, "r1", 1, 7, service_digest(svcs))
    (data,) = encode_update_parts(origin, LOCATION, 60, svcs)
    result = decode(data)
    assert isinstance(result, Update)
    assert result.origin.digest == service_digest(result.services)


# --------------------------------------------------------------------------------------------
# decode never raises

START_LINES = [b"M-SEARCH * HTTP/1.1\r\n", b"NOTIFY * HTTP/1.1\r\n", b"HTTP/1.1 200 OK\r\n"]


@given(data=st.binary(max_size=MAX_DATAGRAM + 100), fleet=st.none() | st.integers(0, 255))
def test_decode_never_raises_on_random_bytes(data: bytes, fleet: int | None) -> None:
    check_decoded(decode(data, fleet=fleet))


@given(start=st.sampled_from(START_LINES), rest=st.binary(max_size=600))
def test_decode_never_raises_after_a_valid_start_line(start: bytes, rest: bytes) -> None:
    check_decoded(decode(start + rest))


header_names = st.sampled_from(
    sorted(headers_of(corpus()[1]) | headers_of(corpus()[5]) | headers_of(corpus()[2]))
)


@given(
    start=st.sampled_from(START_LINES),
    lines=st.lists(st.tuples(header_names, st.text(max_size=30)), max_size=25),
    body=st.binary(max_size=200),
)
def test_decode_never_raises_on_header_soup(
    start: bytes, lines: list[tuple[str, str]], body: bytes
) -> None:
    head = "".join(f"{name}: {value}\r\n" for name, value in lines).encode("utf-8", "replace")
    check_decoded(decode(start + head + b"\r\n" + body))


@given(
    original=st.sampled_from(corpus()),
    ops=st.lists(
        st.tuples(
            st.sampled_from(["flip", "truncate", "insert", "delete", "duplicate"]),
            st.integers(0, MAX_DATAGRAM),
            st.binary(min_size=1, max_size=8),
        ),
        min_size=1,
        max_size=4,
    ),
    fleet=st.none() | st.integers(0, 5),
)
def test_decode_never_raises_on_mutated_datagrams(
    original: bytes, ops: list[tuple[str, int, bytes]], fleet: int | None
) -> None:
    data = bytearray(original)
    for op, where, chunk in ops:
        at = where % (len(data) + 1)
        if op == "flip" and data:
            data[at % len(data)] ^= chunk[0] or 0x20
        elif op == "truncate":
            del data[at:]
        elif op == "insert":
            data[at:at] = chunk
        elif op == "delete":
            del data[at : at + len(chunk)]
        else:
            data[at:at] = data[at : at + 40]
    result = decode(bytes(data), fleet=fleet)
    check_decoded(result)
    if not isinstance(result, Reject) and fleet is not None and result.origin is not None:
        assert result.origin.fleet == fleet


def test_delta_update_round_trip_and_rules() -> None:
    origin = Origin(3, "r1", 2, 8, "0123456789abcdef")
    added = (Service("n1", "new", "sensor.x", None, {"k": 1}),)
    delta = Update(origin, "http://10.3.0.1:8701/d", 30, 0, 1, added, base=7, removed=("a", "b"))
    data = encode(delta)
    assert b"X-SDFR-BASE: 7\r\n" in data and b'"removed":["a","b"]' in data
    assert decode(data) == delta
    # A whole set's part carries no "removed"; a delta is one part, based below its version.
    whole = Update(origin, "http://10.3.0.1:8701/d", 30, 0, 1, added)
    assert decode(encode(whole)) == whole
    with pytest.raises(ValueError):
        encode(Update(origin, "http://x/", 30, 0, 1, added, removed=("a",)))
    with pytest.raises(ValueError):
        encode(Update(origin, "http://x/", 30, 0, 1, added, base=8))
    with pytest.raises(ValueError):
        encode(Update(origin, "http://x/", 30, 0, 2, added, base=1))
    forged = encode(whole).replace(b'"services":[', b'"removed":["a"],"services":[')
    forged = forged.replace(
        b"CONTENT-LENGTH: " + str(len(encode(whole).split(b"\r\n\r\n", 1)[1])).encode(),
        b"CONTENT-LENGTH: " + str(len(forged.split(b"\r\n\r\n", 1)[1])).encode(),
    )
    rejected = decode(forged)
    assert isinstance(rejected, Reject) and rejected.reason == "bad-body"
    bad_base = data.replace(b"X-SDFR-BASE: 7", b"X-SDFR-BASE: 9")
    rejected = decode(bad_base)
    assert isinstance(rejected, Reject) and rejected.reason == "bad-value"
