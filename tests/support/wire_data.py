"""Strategies and helpers for the codec's tests: origins, texts, realistic services, a corpus
of real datagrams, and edits of a datagram's headers."""

from __future__ import annotations

import json
import random

from hypothesis import strategies as st

from sdfr.records.model import Service
from sdfr.wire import (
    REJECT_REASONS,
    WANT_ALL,
    Alive,
    Byebye,
    Discovery,
    Message,
    Origin,
    Reject,
    Response,
    Update,
    encode,
    fleet_target,
)

# --------------------------------------------------------------------------------------------
# Strategies

robot_ids = st.from_regex(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}", fullmatch=True)
origins = st.builds(
    Origin,
    fleet=st.integers(0, 255),
    robot_id=robot_ids,
    boot_id=st.integers(0, 2**31 - 1),
    version=st.integers(0, 2**53),
    digest=st.text("0123456789abcdef", min_size=16, max_size=16),
)
# Header values: printable, no surrounding whitespace; ASCII and some unicode.
header_texts = st.one_of(
    st.from_regex(r"[!-~]([ -~]{0,60}[!-~])?", fullmatch=True),
    st.text(st.characters(categories=("L", "N", "P", "S")), min_size=1, max_size=30),
)
locations = st.from_regex(r"http://[a-z0-9.-]{1,40}:[0-9]{1,5}/[!-~]{0,100}", fullmatch=True)
max_ages = st.integers(1, 86400)
seqs = st.none() | st.integers(0, 2**53)
wants = st.one_of(
    st.none(),
    st.just(WANT_ALL),
    st.lists(st.integers(0, 255), min_size=1, max_size=60, unique=True).map(
        lambda xs: tuple(sorted(xs))
    ),
)
#: Text a service may hold: anything but control characters (sdfr.records.model.CONTROL_CHARS).
printable = st.characters(blacklist_categories=("Cc", "Cs", "Zl", "Zp"))
attr_values = st.one_of(
    st.text(printable, max_size=20),
    st.integers(-(2**53), 2**53),
    st.floats(allow_nan=False, allow_infinity=False),
    st.booleans(),
)
services = st.builds(
    Service,
    id=st.from_regex(r"[A-Za-z0-9._-]{1,24}", fullmatch=True),
    name=st.text(printable, min_size=1, max_size=30).filter(lambda s: bool(s.strip())),
    type=st.from_regex(r"[A-Za-z0-9][A-Za-z0-9._:/-]{0,30}", fullmatch=True),
    url=st.none() | st.text(printable, max_size=40),
    attributes=st.dictionaries(
        st.text(printable, min_size=1, max_size=12), attr_values, max_size=4
    ),
)
service_lists = st.lists(
    services.filter(lambda s: len(json.dumps(s.to_json(), ensure_ascii=False)) < 600),
    max_size=40,
    unique_by=lambda s: s.id,
)

ORIGIN = Origin(fleet=3, robot_id="robot-7", boot_id=1700000000, version=42, digest="0" * 16)
LOCATION = "http://10.0.0.7:8080/sdfr"


def realistic_services(n: int) -> list[Service]:
    """Services of roughly 150 bytes of JSON each, as a ROS robot might announce."""
    return [
        Service(
            id=f"svc-{i:03d}",
            name=f"Camera {i} (front)",
            type="ros2/topic",
            url=f"ros2://robot-7/camera_{i}/image_raw",
            attributes={"encoding": "rgb8", "rate": 30, "frame": f"cam_{i}_link"},
        )
        for i in range(n)
    ]


def noisy_services(n: int, seed: int = 0, size: int = 100) -> list[Service]:
    """Services whose names and urls are random hex (`size` characters of them each): sets
    that deflate little, unlike `realistic_services`, so a set takes as many parts as its
    JSON says in either wire form."""
    rng = random.Random(seed)
    return [
        Service(
            id=f"n{i:04d}",
            name=rng.randbytes(size // 4).hex(),
            type="ros2/topic",
            url=rng.randbytes(size // 4).hex(),
        )
        for i in range(n)
    ]


def corpus() -> list[bytes]:
    """One valid datagram of each kind, to mutate."""
    svcs = realistic_services(3)
    return [
        encode(Discovery(None, "ssdp:all", 3)),
        encode(Discovery(ORIGIN, fleet_target(3), 2, seq=9, want=(0, 2), want_version=42)),
        encode(Response(ORIGIN, fleet_target(3), LOCATION, 1800, seq=9)),
        encode(Alive(ORIGIN, LOCATION, 1800)),
        encode(Byebye(ORIGIN)),
        encode(Update(ORIGIN, LOCATION, 1800, 0, 1, tuple(svcs))),
    ]


def headers_of(data: bytes) -> dict[str, str]:
    head = data.split(b"\r\n\r\n", 1)[0].decode()
    lines = head.split("\r\n")[1:]
    return {k.upper(): v.strip() for k, _, v in (line.partition(":") for line in lines)}


def edit(data: bytes, drop: tuple[str, ...] = (), **values: str) -> bytes:
    """`data` with headers dropped or replaced/added (underscores in names become dashes;
    use `BOOTID_UPNP_ORG`-style names via the dict form)."""
    head, sep, body = data.partition(b"\r\n\r\n")
    lines = head.decode().split("\r\n")
    changes = {k.replace("__", ".").replace("_", "-").upper(): v for k, v in values.items()}
    out = [lines[0]]
    for line in lines[1:]:
        name = line.partition(":")[0].strip().upper()
        if name in drop:
            continue
        if name in changes:
            out.append(f"{name}: {changes.pop(name)}")
        else:
            out.append(line)
    out += [f"{k}: {v}" for k, v in changes.items()]
    return "\r\n".join(out).encode() + sep + body


def check_reject(result: Message | Reject, reason: str, detail: str = "") -> None:
    assert isinstance(result, Reject), result
    assert result.reason == reason, result
    assert detail in result.detail, result


def check_decoded(result: Message | Reject) -> None:
    """What every decode result must look like, whatever went in."""
    if isinstance(result, Reject):
        assert result.reason in REJECT_REASONS
        assert not result.detail.startswith("internal error"), result.detail
    else:
        assert isinstance(result, Discovery | Response | Update | Alive | Byebye)


ASYNC_UPNP_CLIENT_SEARCH = (
    b"M-SEARCH * HTTP/1.1\r\n"
    b"HOST: 239.255.255.250:1900\r\n"
    b'MAN: "ssdp:discover"\r\n'
    b"MX: 4\r\n"
    b"ST: ssdp:all\r\n"
    b"\r\n"
)
