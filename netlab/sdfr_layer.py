"""A scapy layer for SDfR datagrams (UDP port 1900), dissected by `sdfr.wire.decode`.

Importing this module imports scapy and binds `SDfR` to UDP source and destination port 1900,
so ``Ether(frame)`` or a `PcapReader` yields ``Ether / IP / UDP / SDfR``.  There is one parser:
the layer's fields are a view of what `sdfr.wire.decode` makes of the datagram, and a datagram
it rejects dissects as ``msg_type="Reject"`` with the reason; dissection never raises.

The datagram itself is the `load` field (so ``pkt[UDP].load`` works as with a Raw payload);
building a packet emits `load` unchanged.  Make one from a message with
``SDfR(sdfr.wire.encode(msg))``.

`netlab.datagram.describe` gives the same fields without scapy, for code that has the bytes.
"""

from __future__ import annotations

from typing import Any, ClassVar

from scapy.fields import Field
from scapy.layers.inet import UDP
from scapy.packet import Packet, bind_layers

from netlab.datagram import MSG_TYPES, PORT, VIEW_FIELDS, describe, view

__all__ = ["MSG_TYPES", "PORT", "SDfR", "describe"]


class _ViewField(Field[Any, Any]):
    """A value read from the datagram (str, int or None); it adds no bytes of its own."""

    def __init__(self, name: str) -> None:
        super().__init__(name, None, fmt="B")

    def any2i(self, pkt: Any, x: Any) -> Any:
        return x

    def i2repr(self, pkt: Any, x: Any) -> str:
        return "" if x is None else repr(x) if isinstance(x, str) else str(x)

    def addfield(self, pkt: Any, s: bytes, val: Any) -> bytes:
        return s

    def getfield(self, pkt: Any, s: bytes) -> tuple[bytes, Any]:
        return s, None


class _LoadField(Field[Any, Any]):
    """The whole datagram."""

    def __init__(self, name: str) -> None:
        super().__init__(name, b"", fmt="B")

    def any2i(self, pkt: Any, x: Any) -> bytes:
        return x.encode() if isinstance(x, str) else bytes(x or b"")

    def i2repr(self, pkt: Any, x: Any) -> str:
        return f"<{len(x or b'')} bytes>"

    def i2len(self, pkt: Any, x: Any) -> int:
        return len(x or b"")

    def addfield(self, pkt: Any, s: bytes, val: Any) -> bytes:
        return s + bytes(val or b"")

    def getfield(self, pkt: Any, s: bytes) -> tuple[bytes, bytes]:
        return b"", s


class SDfR(Packet):
    """One SDfR (or plain SSDP) datagram; the fields are read-only views of `load`.

    start: the start line (at most 80 characters); method: M-SEARCH, NOTIFY or RESPONSE;
    msg_type: one of MSG_TYPES; robot, fleet, boot, version: the sender (None for a plain
    SSDP search); part (0-based), parts, services: Update only; st, seq: Discovery and
    Response (seq marks a unicast ping); ping: a ping riding on a Response (its sequence
    number); key, counter: the seal of a keyed fleet's datagram (the key id and the sender's
    counter, as written: a capture holds no key to check them); reason, detail: Reject only.
    """

    name = "SDfR"
    fields_desc: ClassVar[list[Any]] = [*(_ViewField(n) for n in VIEW_FIELDS), _LoadField("load")]

    def do_dissect(self, s: bytes) -> bytes:
        data = bytes(s)
        values = view(data)
        # Only what the datagram has: None fields stay at their default, out of repr().
        self.fields.update((k, v) for k, v in values.items() if v is not None)
        self.fields["load"] = data
        self.raw_packet_cache = data
        self.raw_packet_cache_fields = {}
        self.explicit = 1
        return b""

    def self_build(self) -> bytes:
        return bytes(self.fields.get("load", b""))

    def extract_padding(self, s: bytes) -> tuple[bytes, bytes | None]:
        return b"", None

    def mysummary(self) -> str:
        f = self.fields
        kind = f.get("msg_type") or "?"
        if kind == "Reject":
            return f"SDfR Reject {f.get('reason')}: {f.get('detail') or ''}"[:120]
        words = [f"SDfR {kind}"]
        if kind in ("Discovery", "Response") and f.get("seq") is not None:
            words[0] += " (ping)" if kind == "Discovery" else " (pong)"
        if f.get("robot") is not None:
            words.append(f"{f['robot']} fleet={f['fleet']} boot={f['boot']} v={f['version']}")
        if kind == "Update":
            words.append(f"part {f['part'] + 1}/{f['parts']} ({f['services']} services)")
        if kind in ("Discovery", "Response"):
            words.append(f"st={f.get('st')}")
            if f.get("seq") is not None:
                words.append(f"seq={f['seq']}")
        return " ".join(words)


bind_layers(UDP, SDfR, dport=PORT)
bind_layers(UDP, SDfR, sport=PORT)
