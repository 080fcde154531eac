"""The radio stand-in: a bridge in the air namespace, and one nftables table saying who hears whom.

Each robot's veth has its air-side end (``v<robot>``) enslaved to the
bridge ``br0`` in ``nl-<lab>-air``. The bridge lives in its own namespace
because a bridge in the root namespace is at the mercy of the host's
br_netfilter settings (Docker makes it drop everything).

Connectivity is the ``bridge netlab`` table's forward chain, policy drop:
a frame from port A leaves on port B only if (A, B) is in the ``pairs``
verdict map, whose verdict is ``accept`` or a jump to ``loss_<bp>`` (drop
with probability bp/10000, else accept). Flooded frames (multicast,
broadcast, ARP) pass the forward hook once per output port, so the same
per-pair rule applies to them as to unicast. One map lookup per frame and
port scales to 50 robots (2,450 pairs) where a linear rule list would
not. The whole table is replaced in one `nft -f` transaction, so a change
never shows a half-loaded state.
"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping

from pyroute2 import IPRoute

from netlab import kernel
from netlab.errors import KernelError, kernel_errors
from netlab.naming import BRIDGE, ROBOT_IFACE
from netlab.ranges import Pair

TABLE = "netlab"
#: Loss resolution of the nft rules: 1/LOSS_SCALE, i.e. 0.01 %.
LOSS_SCALE = 10000


def loss_units(loss: float) -> int:
    """Loss in percent as the drop threshold of `numgen random mod LOSS_SCALE`."""
    return max(0, min(LOSS_SCALE, round(loss * LOSS_SCALE / 100)))


def ruleset(links: Mapping[Pair, float], ports: Mapping[str, str], table: str = TABLE) -> str:
    """The nft script that replaces `table` with one allowing exactly `links`.

    `links` maps ordered (sender, receiver) robot pairs to a loss in percent;
    `ports` maps robots to their bridge port. Pairs whose loss rounds to 100 %
    are left out (the policy drops them).
    """
    verdicts: list[str] = []
    chains: set[int] = set()
    for (a, b), loss in sorted(links.items()):
        units = loss_units(loss)
        if units >= LOSS_SCALE:
            continue
        if units == 0:
            verdict = "accept"
        else:
            verdict = f"jump loss_{units}"
            chains.add(units)
        verdicts.append(f'"{ports[a]}" . "{ports[b]}" : {verdict}')
    lines = [
        # Declaring the table first makes the delete valid when it does not exist yet.
        f"table bridge {table}",
        f"delete table bridge {table}",
        f"table bridge {table} {{",
    ]
    for units in sorted(chains):
        lines += [
            f"\tchain loss_{units} {{",
            f"\t\tnumgen random mod {LOSS_SCALE} < {units} drop",
            "\t\taccept",
            "\t}",
        ]
    lines += ["\tmap pairs {", "\t\ttype ifname . ifname : verdict"]
    if verdicts:
        lines.append("\t\telements = {")
        lines += [f"\t\t\t{v}," for v in verdicts]
        lines.append("\t\t}")
    lines += [
        "\t}",
        "\tchain forward {",
        "\t\ttype filter hook forward priority 0; policy drop;",
        "\t\tiifname . oifname vmap @pairs",
        "\t}",
        "}",
    ]
    return "\n".join(lines) + "\n"


class Medium:
    """The bridge in namespace `ns` and its nft table; `load` applies a set of links."""

    def __init__(self, ns: str) -> None:
        self.ns = ns
        self._ipr: IPRoute | None = None
        self._bridge = 0
        self._loaded: str | None = None

    @property
    def ipr(self) -> IPRoute:
        if self._ipr is None:
            raise KernelError(f"the medium {self.ns} is not up")
        return self._ipr

    def create(self) -> None:
        """Create the namespace, the bridge and an empty (drop everything) table."""
        self._ipr = ipr = kernel.create_ns(self.ns)
        with kernel.inside(self.ns):
            # IPv4 only: IPv6 autoconfiguration chatter would only clutter captures.
            kernel.set_sysctl("net.ipv6.conf.all.disable_ipv6", "1")
            kernel.set_sysctl("net.ipv6.conf.default.disable_ipv6", "1")
        with kernel_errors(f"creating the bridge in {self.ns}"):
            ipr.link("set", index=ipr.link_lookup(ifname="lo")[0], state="up")
            # No multicast snooping: the medium floods multicast like a radio,
            # whatever the IGMP membership timers say.
            ipr.link("add", ifname=BRIDGE, kind="bridge", br_mcast_snooping=0, state="up")
            self._bridge = ipr.link_lookup(ifname=BRIDGE)[0]
        self.load({}, {})

    def open(self) -> None:
        """Take over the medium of a lab that is up (made by another process)."""
        self._ipr = kernel.open_ns(self.ns)
        with kernel_errors(f"finding the bridge in {self.ns}"):
            self._bridge = self._ipr.link_lookup(ifname=BRIDGE)[0]

    def attach(self, robot_ns: str, port: str, mac: str) -> None:
        """A veth from the bridge (`port`) to `eth0` with `mac` in `robot_ns`."""
        with kernel_errors(f"linking {robot_ns} to the medium"):
            self.ipr.link(
                "add",
                ifname=port,
                kind="veth",
                master=self._bridge,
                state="up",
                peer={"ifname": ROBOT_IFACE, "net_ns_fd": robot_ns, "address": mac},
            )

    def ifindex(self, port: str) -> int:
        found = self.ipr.link_lookup(ifname=port)
        if not found:
            raise KernelError(f"no port {port} on the medium {self.ns}")
        return int(found[0])

    def load(self, links: Mapping[Pair, float], ports: Mapping[str, str]) -> bool:
        """Make the table allow exactly `links`; False if it already did."""
        text = ruleset(links, ports)
        if text == self._loaded:
            return False
        kernel.run_in_ns(
            self.ns, ["nft", "-f", "-"], f"loading the medium rules in {self.ns}", text
        )
        self._loaded = text
        return True

    def rules(self) -> str:
        """The table as the kernel has it now (`nft list table`)."""
        return kernel.run_in_ns(
            self.ns, ["nft", "list", "table", "bridge", TABLE], f"listing {TABLE} in {self.ns}"
        )

    def close(self) -> None:
        if self._ipr is not None:
            with contextlib.suppress(Exception):
                self._ipr.close()
            self._ipr = None
