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
from netlab.vxlan import PORT_NAME as SPAN_PORT
from netlab.vxlan import Span

TABLE = "netlab"
#: Loss resolution of the nft rules: 1/LOSS_SCALE, i.e. 0.01 %.
LOSS_SCALE = 10000


def loss_units(loss: float) -> int:
    """Loss in percent as the drop threshold of `numgen random mod LOSS_SCALE`."""
    return max(0, min(LOSS_SCALE, round(loss * LOSS_SCALE / 100)))


def ruleset(
    links: Mapping[Pair, float],
    ports: Mapping[str, str],
    table: str = TABLE,
    remote: Mapping[str, str] | None = None,
    span_port: str | None = None,
) -> str:
    """The nft script that replaces `table` with one allowing exactly `links`.

    `links` maps ordered (sender, receiver) robot pairs to a loss in percent;
    `ports` maps robots to their bridge port. Pairs whose loss rounds to 100 %
    are left out (the policy drops them).

    A medium spanning hosts (`netlab.vxlan`) has the other hosts' robots in `remote`
    (robot -> MAC), all behind the bridge port `span_port`: a frame from one of them is
    judged by its source MAC and the local receiver's port (the ``remote`` map); a frame
    leaving through `span_port` passes (its receiver's host judges it).  Pairs between two
    remote robots are left to their hosts.
    """
    remote = remote or {}
    verdicts: list[str] = []
    from_afar: list[str] = []
    chains: set[int] = set()
    for (a, b), loss in sorted(links.items()):
        units = loss_units(loss)
        if units >= LOSS_SCALE or b in remote or (a in remote and span_port is None):
            continue
        if units == 0:
            verdict = "accept"
        else:
            verdict = f"jump loss_{units}"
            chains.add(units)
        if a in remote:
            from_afar.append(f'{remote[a]} . "{ports[b]}" : {verdict}')
        else:
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
    lines += _map("pairs", "ifname . ifname", verdicts)
    if span_port is not None:
        lines += _map("remote", "ether_addr . ifname", from_afar)
    lines += [
        "\tchain forward {",
        "\t\ttype filter hook forward priority 0; policy drop;",
    ]
    if span_port is not None:
        lines += [
            f'\t\tiifname "{span_port}" ether saddr . oifname vmap @remote',
            f'\t\toifname "{span_port}" accept',
        ]
    lines += [
        "\t\tiifname . oifname vmap @pairs",
        "\t}",
        "}",
    ]
    return "\n".join(lines) + "\n"


def _map(name: str, key: str, elements: list[str]) -> list[str]:
    lines = [f"\tmap {name} {{", f"\t\ttype {key} : verdict"]
    if elements:
        lines.append("\t\telements = {")
        lines += [f"\t\t\t{v}," for v in elements]
        lines.append("\t\t}")
    return [*lines, "\t}"]


class Medium:
    """The bridge in namespace `ns` and its nft table; `load` applies a set of links."""

    def __init__(self, ns: str) -> None:
        self.ns = ns
        self._ipr: IPRoute | None = None
        self._bridge = 0
        self._loaded: str | None = None
        #: The bridge port joining this medium to the other hosts' (`span`), if any.
        self.span_port: str | None = None

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

    def span(self, span: Span, ifname: str = SPAN_PORT) -> None:
        """Join this medium to the other hosts' (see `netlab.vxlan`): the VXLAN device is made
        in the calling process's namespace (the one with the underlay), moved onto the bridge,
        and told to flood group frames to every other host."""
        doing = f"joining the medium {self.ns} to the other hosts over VXLAN {span.vni}"
        kernel.run_argv(span.create_argv(ifname), doing)
        try:
            kernel.run_argv(["ip", "link", "set", ifname, "netns", self.ns], doing)
        except KernelError:
            kernel.run_argv(["ip", "link", "del", ifname], doing)
            raise
        for argv in span.flood_argvs(ifname):
            kernel.run_in_ns(self.ns, argv, doing)
        kernel.run_in_ns(self.ns, ["ip", "link", "set", ifname, "master", BRIDGE, "up"], doing)
        self.span_port = ifname

    def load(
        self,
        links: Mapping[Pair, float],
        ports: Mapping[str, str],
        remote: Mapping[str, str] | None = None,
    ) -> bool:
        """Make the table allow exactly `links` (with the other hosts' robots, by MAC, in
        `remote` when spanned); False if it already did."""
        text = ruleset(links, ports, remote=remote, span_port=self.span_port)
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
