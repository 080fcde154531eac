"""Per-robot link shaping: netem where the kernel has it, nftables loss and tbf rate where not.

A robot's link is shaped in both directions, like a radio: a root qdisc on
its ``eth0`` shapes what it sends, and the same qdisc on its port in the
air namespace shapes what it receives. So 50 ms of delay gives a 100 ms
round trip to a clean robot, and 30 % loss loses 30 % of the datagrams it
sends and 30 % of those it receives.

Without netem (``sch_netem``), loss is applied by the medium's nftables
rules on every pair from or to the robot, and rate by a tbf qdisc; delay,
jitter, duplicate, reorder and corrupt raise ShapingUnsupported. A
parameter is never silently ignored.
"""

from __future__ import annotations

import errno
import math
import re
from dataclasses import dataclass, fields
from typing import Any

from pyroute2 import IPRoute
from pyroute2.netlink.exceptions import NetlinkError
from pyroute2.netlink.rtnl import TC_H_ROOT
from pyroute2.netlink.rtnl.tcmsg import sched_netem

from netlab import kernel
from netlab.doctor import Capabilities
from netlab.errors import InvalidShapeError, ShapingUnsupported, kernel_errors


def _netem_rate_is_an_option(request: dict[str, Any]) -> None:
    request.pop("rate", None)


# pyroute2 (0.9.x) turns netem's `rate` into TCA_OPTIONS/TCA_NETEM_RATE but leaves the
# key in the request too, which it then encodes as the message's TCA_RATE attribute and
# fails (TypeError: object of type 'int' has no len()). Its tbf, htb and cake plugins
# drop the key after use in a `fix_request` hook; give netem the same.
if not hasattr(sched_netem, "fix_request"):
    sched_netem.fix_request = _netem_rate_is_an_option

ROOT_HANDLE = 0x10000  # 1:0
NETEM_LIMIT = 1000  # packets, netem's own default
TBF_LATENCY_US = 50_000  # longest a packet may wait in the token bucket
MTU_FRAME = 1514

#: Parameters only netem can do.
NETEM_ONLY = ("delay", "jitter", "duplicate", "reorder", "corrupt")

_RATE_RE = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*([kmg]?)(bit|bps)?\s*$", re.IGNORECASE)
_RATE_UNITS = {"": 1, "k": 10**3, "m": 10**6, "g": 10**9}


def parse_rate(rate: int | float | str) -> int:
    """Bits per second from an int or a string like '1mbit', '500kbit', '2Mbps' (bytes)."""
    if isinstance(rate, bool):
        raise InvalidShapeError(f"rate: expected bits per second, got {rate!r}")
    if isinstance(rate, int | float):
        bits = float(rate)
    else:
        m = _RATE_RE.match(rate)
        if m is None:
            raise InvalidShapeError(
                f"rate: expected bits per second or a string like '1mbit', got {rate!r}"
            )
        bits = float(m.group(1)) * _RATE_UNITS[m.group(2).lower()]
        if (m.group(3) or "bit").lower() == "bps":
            bits *= 8
    if not (math.isfinite(bits) and bits >= 8):
        raise InvalidShapeError(f"rate: must be at least 8 bit/s, got {rate!r}")
    return int(bits)


@dataclass(frozen=True, slots=True)
class LinkShape:
    """Impairments of one robot's link; all zero/None is no shaping at all.

    delay and jitter in milliseconds; loss, duplicate, reorder and corrupt in
    percent (0-100); rate in bits per second.
    """

    delay: float = 0.0
    jitter: float = 0.0
    loss: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    corrupt: float = 0.0
    rate: int | None = None

    def __post_init__(self) -> None:
        for name in ("delay", "jitter"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0 <= value <= 60_000):
                raise InvalidShapeError(f"{name}: must be 0-60000 ms, got {value}")
        for name in ("loss", "duplicate", "reorder", "corrupt"):
            value = getattr(self, name)
            if not 0 <= value <= 100:
                raise InvalidShapeError(f"{name}: must be 0-100 %, got {value}")
        if self.jitter and not self.delay:
            raise InvalidShapeError("jitter: needs a delay to vary around (delay > 0)")
        if self.reorder and not self.delay:
            # netem reorders by sending some packets at once while the rest wait.
            raise InvalidShapeError("reorder: needs a delay (packets overtake delayed ones)")
        if self.rate is not None and self.rate < 8:
            raise InvalidShapeError(f"rate: must be at least 8 bit/s, got {self.rate}")

    @classmethod
    def of(cls, **params: Any) -> LinkShape:
        """Build from keyword arguments, naming any unknown one; rate may be a string."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(params) - known)
        if unknown:
            raise InvalidShapeError(
                f"unknown shaping parameter(s) {', '.join(unknown)}; "
                f"known: {', '.join(sorted(known))}"
            )
        if params.get("rate") is not None:
            params["rate"] = parse_rate(params["rate"])
        try:
            return cls(**{k: v for k, v in params.items() if v is not None or k == "rate"})
        except TypeError as exc:
            raise InvalidShapeError(f"shaping parameters: {exc}") from None

    @property
    def is_none(self) -> bool:
        return self == LinkShape()

    def netem_only(self) -> list[str]:
        """The parameters set here that only netem can apply."""
        return [name for name in NETEM_ONLY if getattr(self, name)]


def netem_options(shape: LinkShape) -> dict[str, object]:
    """Keyword arguments of pyroute2's `tc(..., kind="netem")` for `shape`.

    pyroute2 takes delay and jitter in microseconds, percentages as floats,
    and the netem rate in bytes per second.
    """
    opts: dict[str, Any] = {
        "limit": NETEM_LIMIT,
        "delay": round(shape.delay * 1000),
        "jitter": round(shape.jitter * 1000),
        "loss": shape.loss,
        "duplicate": shape.duplicate,
    }
    if shape.reorder:
        opts["prob_reorder"] = shape.reorder
    if shape.corrupt:
        opts["prob_corrupt"] = shape.corrupt
    if shape.rate is not None:
        opts["rate"] = max(1, shape.rate // 8)
    return opts


def tbf_options(rate: int) -> dict[str, object]:
    """Keyword arguments of pyroute2's `tc(..., kind="tbf")` for `rate` bits per second.

    The bucket holds 10 ms of traffic but at least two full frames, or it
    could never pass a frame; packets wait at most TBF_LATENCY_US.
    """
    byte_rate = max(1, rate // 8)
    return {
        "rate": byte_rate,
        "burst": max(2 * MTU_FRAME, byte_rate // 100),
        "latency": TBF_LATENCY_US,
    }


@dataclass(frozen=True, slots=True)
class ShapePlan:
    """How a LinkShape is realised on this kernel."""

    kind: str | None  # the root qdisc: "netem", "tbf" or None (none)
    options: dict[str, Any]
    nft_loss: float  # loss the medium's rules apply to pairs from/to the robot


def plan(shape: LinkShape, caps: Capabilities) -> ShapePlan:
    """Decide qdisc and medium loss for `shape`, or raise ShapingUnsupported naming the module."""
    if shape.is_none:
        return ShapePlan(None, {}, 0.0)
    if caps.netem:
        return ShapePlan("netem", netem_options(shape), 0.0)
    missing = shape.netem_only()
    if missing:
        raise ShapingUnsupported(
            f"{', '.join(missing)}: needs the kernel's netem qdisc (module sch_netem), which "
            "this kernel does not have (see `netlab doctor`). Use a kernel with sch_netem "
            "(most distribution kernels: `modprobe sch_netem`), or the VM tier "
            "(`make test-netem` boots a Debian kernel under virtme-ng). Without netem, "
            "netlab shapes loss (nftables) and rate (tbf) only."
        )
    if shape.loss and not (caps.nft_bridge and caps.numgen):
        raise ShapingUnsupported(
            "loss: without netem it needs nftables' bridge family and numgen "
            "(modules nf_tables, nft_numgen), which this kernel lacks (see `netlab doctor`)"
        )
    if shape.rate is not None and not caps.tbf:
        raise ShapingUnsupported(
            "rate: without netem it needs the tbf qdisc (module sch_tbf), which this kernel "
            "lacks (see `netlab doctor`)"
        )
    if shape.rate is not None:
        return ShapePlan("tbf", tbf_options(shape.rate), shape.loss)
    return ShapePlan(None, {}, shape.loss)


def apply(ipr: IPRoute, index: int, shape_plan: ShapePlan, where: str) -> None:
    """Make the plan's qdisc the root qdisc of interface `index` (`where`), or remove it."""
    if shape_plan.kind is None:
        try:
            ipr.tc("del", index=index, parent=TC_H_ROOT)
        except NetlinkError as exc:
            # Nothing to delete: the interface already has its default qdisc.
            if exc.code not in (errno.ENOENT, errno.EINVAL):
                with kernel_errors(f"removing the shaping of {where}"):
                    raise
        return
    with kernel_errors(f"shaping {where} with {shape_plan.kind}"):
        ipr.tc(
            "replace", kind=shape_plan.kind, index=index, handle=ROOT_HANDLE, **shape_plan.options
        )


def apply_in_ns(ns: str, ifname: str, shape_plan: ShapePlan, where: str) -> None:
    """`apply` to interface `ifname` of network namespace `ns`."""
    ipr = kernel.open_ns(ns)
    try:
        apply(ipr, ipr.link_lookup(ifname=ifname)[0], shape_plan, where)
    finally:
        ipr.close()
