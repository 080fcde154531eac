"""One lab's medium across hosts: a kernel VXLAN port on each host's medium bridge.

Each host of a lab has its own medium (a bridge in its own namespace, `netlab.medium`) with
its own robots on it.  The media are joined by one VXLAN segment per lab (`Span`: its VNI and
UDP port), made on each host in the namespace that has the underlay (where the host's SSH
session runs) and then moved into the medium's namespace as the bridge port ``vx0``: its
socket stays on the underlay.  Group frames (multicast, broadcast, unknown unicast) reach
every other host by head-end replication (one all-zeros forwarding entry per other host);
unicast goes where the bridge learnt the destination.

The verdict of each (sender, receiver) pair is applied once, on the receiving host: a frame
leaving a host through ``vx0`` always passes, and a frame arriving through ``vx0`` is judged
by its sender's MAC and the receiving robot's port (`netlab.medium.ruleset`'s ``remote``
map), since every remote robot arrives through the same port.

VXLAN over IPv4 adds 50 bytes to each frame: the robots' interfaces get an MTU of the
underlay's minus 50 (`robot_mtu`), and an underlay too small for a useful robot MTU is
refused, saying so.
"""

from __future__ import annotations

import hashlib
import ipaddress
from collections.abc import Sequence
from dataclasses import dataclass

from netlab.errors import NetlabError

PORT_NAME = "vx0"
#: IANA's VXLAN port.
DEFAULT_PORT = 4789
#: What VXLAN over IPv4 adds to a frame: outer IPv4 (20), UDP (8), VXLAN (8), Ethernet (14).
OVERHEAD = 50
#: The smallest MTU a robot's interface may be left with (IPv4's minimum is 576).
MIN_ROBOT_MTU = 1280


def vni_for(lab: str) -> int:
    """A lab's default VNI (1..2^24-1), derived from its name: two labs apart by default."""
    return int(hashlib.sha256(f"netlab-{lab}".encode()).hexdigest(), 16) % (2**24 - 1) + 1


def robot_mtu(underlay_mtu: int) -> int:
    """The MTU a robot's interface gets on an underlay of `underlay_mtu`; NetlabError when
    the underlay cannot carry a useful one."""
    mtu = underlay_mtu - OVERHEAD
    if mtu < MIN_ROBOT_MTU:
        raise NetlabError(
            f"the underlay's MTU {underlay_mtu} leaves the robots {mtu} after VXLAN's "
            f"{OVERHEAD} bytes; at least {MIN_ROBOT_MTU + OVERHEAD} is needed"
        )
    return mtu


def _address(text: str, what: str) -> str:
    try:
        return str(ipaddress.IPv4Address(text))
    except ValueError:
        raise NetlabError(f"{what}: not an IPv4 address: {text!r}") from None


@dataclass(frozen=True, slots=True)
class Span:
    """This host's end of a lab's VXLAN: its underlay address, the other hosts' addresses."""

    vni: int
    local: str
    peers: tuple[str, ...]
    port: int = DEFAULT_PORT
    underlay_mtu: int = 1500

    def __post_init__(self) -> None:
        if not 1 <= self.vni < 2**24:
            raise NetlabError(f"VXLAN: a VNI is 1 to {2**24 - 1}, got {self.vni}")
        if not 1 <= self.port <= 65535:
            raise NetlabError(f"VXLAN: a UDP port is 1 to 65535, got {self.port}")
        _address(self.local, "VXLAN local address")
        for peer in self.peers:
            _address(peer, "VXLAN peer")
        if self.local in self.peers:
            raise NetlabError(f"VXLAN: {self.local} is this host's own address, not a peer")
        robot_mtu(self.underlay_mtu)

    @property
    def mtu(self) -> int:
        """The robots' (and the VXLAN port's) MTU."""
        return robot_mtu(self.underlay_mtu)

    def create_argv(self, ifname: str) -> list[str]:
        """``ip link add``: the VXLAN device, in the namespace that has the underlay."""
        return [
            "ip", "link", "add", ifname, "mtu", str(self.mtu), "type", "vxlan",
            "id", str(self.vni), "local", self.local, "dstport", str(self.port),
        ]  # fmt: skip

    def flood_argvs(self, ifname: str) -> list[list[str]]:
        """``bridge fdb append``: head-end replication of group frames to every other host."""
        return [
            ["bridge", "fdb", "append", "00:00:00:00:00:00", "dev", ifname, "dst", peer]
            for peer in self.peers
        ]


def span_of(lab: str, local: str, hosts: Sequence[str], **kw: int) -> Span:
    """This host's `Span` of `lab` among the underlay addresses `hosts` (its own included)."""
    vni = kw.pop("vni", vni_for(lab))
    return Span(vni, local, tuple(h for h in hosts if h != local), **kw)
