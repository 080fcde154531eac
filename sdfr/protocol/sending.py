"""Sending: a message encoded in the form its receiver reads, sealed when the fleet signs,
and never more bytes to an address that has not proven a round trip than it sent us."""

from __future__ import annotations

from sdfr import wire
from sdfr.protocol import auth
from sdfr.protocol.config import Addr
from sdfr.protocol.state import CoreState
from sdfr.wire import Discovery

#: The header that pads a challenge (`CHALLENGE_PAD` bytes in all).
PAD_HEADER = b"X-SDFR-PAD: "
_PAD_FIXED = len(PAD_HEADER) + 2


def send(
    core: CoreState,
    msg: wire.Message,
    dst: Addr | None,
    *,
    compact: bool | None = None,
    to: str | None = None,
    answer: bool = False,
    pad: int = 0,
) -> bool:
    """Encode and send `msg` (to robot `to` at `dst`; see `emit`): compact when
    `_compact_for(dst)` (or as told), `pad` bytes longer (`PAD_HEADER`)."""
    if compact is None:
        compact = core._compact_for(dst)
    if compact:
        data = wire.encode(msg, compact=True)
    elif isinstance(msg, Discovery) and not msg.multicast and dst is not None:
        # A unicast search names the robot it is sent to in HOST.
        data = wire.encode(msg, group=dst[0], port=dst[1])
    else:
        data = wire.encode(msg, group=core.config.group, port=core.config.port)
    if pad > 0:
        # (Before the blank line; every decoder passes over a header it does not know.)
        data = b"%s%s%s\r\n\r\n" % (data[:-2], PAD_HEADER, b"0" * max(0, pad - _PAD_FIXED))
    kind = type(msg).__name__.lower()
    return emit(core, data, dst, kind, to=to, answer=answer)


def emit(
    core: CoreState,
    data: bytes,
    dst: Addr | None,
    kind: str,
    *,
    to: str | None = None,
    answer: bool = False,
) -> bool:
    """Send `data` to the group (`dst` None) or to robot `to` at `dst`, sealed for it when
    the fleet signs.  An address that has not proven a round trip gets no more bytes than
    it sent us (`_credit`): False, and nothing sent, when this would be more.  `answer`:
    the one standard answer to a plain SSDP search, which its own limits bound."""
    ring = core.keyring
    if ring.signs and ring.primary is not None:
        core._sent_seals += 1
        sender = core._own_host() or ""
        target = None if dst is None else to
        data = auth.seal(data, ring.keys[ring.primary], core._sent_seals, to=target, sender=sender)
    if (
        dst is not None
        and not answer
        and not core._address_proven(dst, core._now)
        and not core._credit.spend(dst[0], len(data))
    ):
        core.counters.rejects["amplification"] += 1
        return False
    core.counters.datagrams_out[kind] += 1
    core.counters.bytes_out += len(data)
    core._out.append((data, dst))
    return True
