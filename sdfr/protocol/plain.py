"""Plain SSDP clients: the one standard answer to a search from our own subnet, read-only
and rate-limited."""

from __future__ import annotations

import ipaddress

from sdfr.protocol import auth, sending
from sdfr.protocol.config import Addr
from sdfr.protocol.state import CoreState
from sdfr.wire import Discovery, Response


def plain_search_allowed(core: CoreState, data: bytes) -> bool:
    """An unsigned plain SSDP search in a keyed fleet, which ssdp_interop may answer."""
    # (No X-SDFR header of any form: a compact search's origin is its X-SDFR line.)
    return core.ssdp_interop and data.startswith(b"M-SEARCH ") and b"X-SDFR" not in data


def on_plain_search(core: CoreState, msg: Discovery, src: Addr, now: float) -> None:
    """A plain SSDP client: its one standard search response, read-only, only on our own
    subnet, and rate-limited per source and in all (the answer is larger than the search:
    no more than that to an address that may be a spoofed victim's)."""
    cfg = core.config
    if not core.ssdp_interop:
        core.counters.rejects["ssdp-interop-off"] += 1
        return
    if not on_subnet(core, src[0]):
        core.counters.rejects["off-subnet"] += 1
        return
    if not core._plain_sources.take(src[0], now) or not core._plain_budget.take(now):
        core.counters.rejects["rate-limited"] += 1
        return
    answer = Response(core._origin(), msg.st, core.location, cfg.max_age)
    sending.send(core, answer, src, compact=False, answer=True)  # a standard client: the full form


def on_subnet(core: CoreState, host: str) -> bool:
    """Whether `host` is on our own subnet (`subnet`; without one, our address's /24)."""
    try:
        addr = ipaddress.ip_address(auth.host_of(host))
        if core.subnet is not None:
            return addr in core.subnet
        own = core._own_host()
        if own is None:
            return False
        prefix = 24 if addr.version == 4 else 64
        return addr in ipaddress.ip_network(f"{auth.host_of(own)}/{prefix}", strict=False)
    except ValueError:
        return False
