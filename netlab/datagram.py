"""What a captured SDfR datagram says, without scapy: `describe` gives the fields of
`netlab.sdfr_layer.SDfR` (the scapy layer is a view of it) from the datagram's bytes, through
`sdfr.wire.decode`, the daemon's own parser.  Reading a capture needs no scapy for it.
"""

from __future__ import annotations

from typing import Any

from sdfr import wire
from sdfr.protocol import auth

__all__ = ["MSG_TYPES", "PORT", "VIEW_FIELDS", "describe", "view"]

PORT = wire.DEFAULT_PORT
#: Every value of the `msg_type` field.
MSG_TYPES = (*(kind.capitalize() for kind in wire.MESSAGE_TYPES), "Reject")
_METHODS = {"M-SEARCH": "M-SEARCH", "NOTIFY": "NOTIFY", "HTTP/1.1": "RESPONSE"}


def describe(data: bytes) -> dict[str, Any]:
    """The `SDfR` field values for one datagram (a Reject says why it is not acceptable).

    `part` is 0-based like `sdfr.wire.Update.part`; on the wire it is ``part+1/parts``.
    """
    line = data.split(b"\n", 1)[0].strip().decode("latin-1")[:80]
    out: dict[str, Any] = dict.fromkeys(VIEW_FIELDS)
    out["start"] = line
    out["method"] = _METHODS.get(line.split(" ", 1)[0], "")
    msg = wire.decode(data)
    out["msg_type"] = type(msg).__name__
    sealed = auth.seal_of(data)
    if sealed is not None:  # which key signed it, and its counter (not checked: no key here)
        out["key"] = sealed.kid
        out["counter"] = sealed.counter
    if isinstance(msg, wire.Reject):
        out["reason"] = msg.reason
        out["detail"] = msg.detail
        return out
    origin = msg.origin
    if origin is not None:
        out["robot"] = origin.robot_id
        out["fleet"] = origin.fleet
        out["boot"] = origin.boot_id
        out["version"] = origin.version
    if isinstance(msg, wire.Update):
        out["part"] = msg.part
        out["parts"] = msg.parts
        out["services"] = len(msg.services)
    if isinstance(msg, wire.Discovery | wire.Response):
        out["st"] = msg.st
        out["seq"] = msg.seq
    if isinstance(msg, wire.Response):
        out["ping"] = msg.ping
    return out


VIEW_FIELDS = (
    "start",
    "method",
    "msg_type",
    "robot",
    "fleet",
    "boot",
    "version",
    "part",
    "parts",
    "services",
    "st",
    "seq",
    "ping",
    "key",
    "counter",
    "reason",
    "detail",
)


def view(data: bytes) -> dict[str, Any]:
    """`describe`'s fields; never raises (describe is total: this only guards against a bug in
    it, which then reads as a Reject saying so)."""
    try:
        return describe(data)
    except Exception as exc:
        values: dict[str, Any] = dict.fromkeys(VIEW_FIELDS)
        values.update(msg_type="Reject", reason="bad-value", detail=f"internal error: {exc}")
        return values
