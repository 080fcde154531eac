"""Text from the air never carries control characters in: a LOCATION (full and compact forms)
or a compact origin line holding one is a "bad-value" rejection.

A LOCATION is kept in the history map and shown by the API, the CLI, the ROS node and
whatever logs them; a control character in it forges log lines and terminal output (issue 25).
HTTP's own rule (RFC 9110 section 5.5): a field value holds no control character but HTAB, and
only spaces and HTABs around it are whitespace (Python's str.strip() also takes \\x0b, \\x0c
and \\x1c-\\x1f for whitespace: a value that ends in one of them is not clean).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import pytest

from sdfr.records.model import Service
from sdfr.wire import WIRE_COMPACT, Alive, Reject, Response, Update, decode, encode
from tests.support.wire_data import LOCATION, ORIGIN

COMPACT = dataclasses.replace(ORIGIN, wire=WIRE_COMPACT)
SERVICE = Service(id="cam", name="front camera", type="camera/rgb")
HEADER = LOCATION.encode()

#: C0 and DEL; not LF, which ends the header line (what follows it is a line of its own).
CONTROLS = [c for c in map(chr, [*range(0x20), 0x7F]) if c != "\n"]
#: At a value's end, CR is its line end and HTAB is HTTP whitespace: both may be there.
AT_END = [c for c in CONTROLS if c not in "\r\t"]

DATAGRAMS: dict[str, Callable[[], bytes]] = {
    "full alive": lambda: encode(Alive(ORIGIN, LOCATION, 1800, 5)),
    "full update": lambda: encode(Update(ORIGIN, LOCATION, 1800, 0, 1, (SERVICE,))),
    "full response": lambda: encode(Response(ORIGIN, "ssdp:all", LOCATION, 1800)),
    "compact alive": lambda: encode(Alive(COMPACT, LOCATION, 0, 5), compact=True),
    "compact update": lambda: encode(Update(COMPACT, LOCATION, 0, 0, 1, (SERVICE,)), compact=True),
}


def _name(c: str) -> str:
    return f"{ord(c):#04x}"


def _with_location(kind: str, location: bytes) -> bytes:
    data = DATAGRAMS[kind]()
    line = b"LOCATION: " + HEADER + b"\r\n"
    assert data.count(line) == 1, data  # the datagram as made carries it once
    return data.replace(line, b"LOCATION: " + location + b"\r\n")


@pytest.mark.parametrize("kind", list(DATAGRAMS))
def test_the_datagrams_decode_as_made(kind: str) -> None:
    """(So that each rejection below is the control character's doing.)"""
    msg = decode(DATAGRAMS[kind]())
    assert not hasattr(msg, "reason") and getattr(msg, "location", None) == LOCATION, msg


def _not_rejected(forge: Callable[[str], bytes], chars: list[str], field: str) -> list[str]:
    """The characters of `chars` whose forged datagram is not a bad-value naming `field`,
    with what decode made of it."""
    out = []
    for c in chars:
        result = decode(forge(c))
        if not (isinstance(result, Reject) and result.reason == "bad-value"):
            out.append(f"{_name(c)}: {result!r:.120}")
        elif field not in result.detail:
            out.append(f"{_name(c)}: {result!r:.120} (not about {field})")
    return out


@pytest.mark.parametrize("kind", list(DATAGRAMS))
def test_a_location_with_a_control_character_inside_is_rejected(kind: str) -> None:
    def forge(c: str) -> bytes:
        return _with_location(kind, HEADER[:12] + c.encode() + HEADER[12:])

    assert _not_rejected(forge, CONTROLS, "LOCATION") == []


@pytest.mark.parametrize("kind", list(DATAGRAMS))
def test_a_location_ending_in_a_control_character_is_rejected(kind: str) -> None:
    def forge(c: str) -> bytes:
        return _with_location(kind, HEADER + c.encode())

    assert _not_rejected(forge, AT_END, "LOCATION") == []


@pytest.mark.parametrize("kind", list(DATAGRAMS))
def test_a_location_with_a_c1_control_or_a_line_separator_is_rejected(kind: str) -> None:
    """The rest of what the API refuses in every text (sdfr.records.model.CONTROL_CHARS): C1
    controls (0x9b is a terminal's CSI) and the Unicode line and paragraph separators."""

    def forge(c: str) -> bytes:
        return _with_location(kind, HEADER[:12] + c.encode() + HEADER[12:])

    assert _not_rejected(forge, ["\x85", "\x9b", "\u2028", "\u2029"], "LOCATION") == []


# -- the compact origin line: X-SDFR: <type> <fleet> <robot> <boot> <version> <digest> [<seq>]


def _origin_line(data: bytes) -> tuple[int, int]:
    start = data.index(b"\r\nX-SDFR: ") + 2
    return start, data.index(b"\r\n", start)


def _forge_origin_line(at: str, c: str) -> bytes:
    data = DATAGRAMS["compact alive"]()
    start, end = _origin_line(data)
    line = data[start:end]
    robot = f" {COMPACT.robot_id} ".encode()
    if at == "in the robot id":
        line = line.replace(robot, robot[:3] + c.encode() + robot[3:])
    elif at == "for a space":
        line = line.replace(robot, robot[:-1] + c.encode())
    else:  # at the end
        line += c.encode()
    return data[:start] + line + data[end:]


@pytest.mark.parametrize("at", ["in the robot id", "for a space"])
def test_a_compact_origin_line_with_a_control_character_inside_is_rejected(at: str) -> None:
    assert _not_rejected(lambda c: _forge_origin_line(at, c), CONTROLS, "X-SDFR") == []


def test_a_compact_origin_line_ending_in_a_control_character_is_rejected() -> None:
    forged = _not_rejected(lambda c: _forge_origin_line("at the end", c), AT_END, "X-SDFR")
    assert forged == []
