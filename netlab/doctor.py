"""What this kernel can do for netlab, found by trying it in a throwaway namespace.

Never by reading version strings: kernels are configured, not numbered.
The probe namespace is ``nl_doctor_<pid>`` (underscores, so that it can
never match a lab's ``nl-<lab>-`` prefix) and is always removed.
"""

from __future__ import annotations

import errno
import functools
import os
import shutil
import subprocess
from dataclasses import dataclass, field, replace
from pathlib import Path

from pyroute2 import IPRoute, netns
from pyroute2.netlink.exceptions import NetlinkError
from pyroute2.netlink.rtnl import TC_H_ROOT

from netlab import hostlimits, hwsim
from netlab.errors import NetlabError, describe

PROBE_TABLE = "doctor"


@dataclass(frozen=True, slots=True)
class Capabilities:
    """One probe's findings; `why` says why a capability is missing."""

    root: bool = False
    netns: bool = False
    veth_bridge: bool = False
    nft_bridge: bool = False
    numgen: bool = False
    netem: bool = False
    tbf: bool = False
    #: Radio labs (`medium radio`): mac80211_hwsim in the kernel, iw and wpa_supplicant.
    radio: bool = False
    gc_thresh3: int = 0  # the host-wide ARP table limit (0: unknown)
    #: Container robots (`--runtime docker`): None when not asked (`probe(docker=True)`).
    docker: bool | None = None
    why: dict[str, str] = field(default_factory=dict)

    @property
    def lab(self) -> bool:
        """Enough for a lab: namespaces, veths into a bridge, a bridge nft table."""
        return self.root and self.netns and self.veth_bridge and self.nft_bridge


def _nft(ns: str, text: str) -> None:
    subprocess.run(
        ["ip", "netns", "exec", ns, "nft", "-f", "-"],
        input=text,
        capture_output=True,
        text=True,
        timeout=30,
        check=True,
    )


def probe(*, docker: bool = False) -> Capabilities:
    """Try each capability in a namespace of its own; never raises.  `docker`: also whether
    container robots can run (Docker answers and has the robot image)."""
    caps = _probe()
    if not docker:
        return caps
    from netlab import docker as engine

    try:
        engine.require_image(engine.DEFAULT_IMAGE)
    except engine.DockerError as exc:
        return replace(caps, docker=False, why={**caps.why, "docker": str(exc)})
    return replace(caps, docker=True)


def _probe() -> Capabilities:
    why: dict[str, str] = {}
    if os.geteuid() != 0:
        return Capabilities(why={"root": "not running as root: netlab needs root (sudo)"})
    missing = [tool for tool in ("ip", "nft") if shutil.which(tool) is None]
    if missing:
        why["tools"] = f"{' and '.join(missing)} not found: apt-get install iproute2 nftables"
    name = f"nl_doctor_{os.getpid()}"
    found: dict[str, bool] = {}
    if name in netns.listnetns():  # left by a killed doctor whose pid we now have
        netns.remove(name)
    try:
        ipr = IPRoute(netns=name, flags=os.O_CREAT | os.O_EXCL)
    except Exception as exc:
        why["netns"] = describe(exc, "creating a network namespace")
        return Capabilities(root=True, why=why)
    try:
        found["netns"] = True
        try:
            ipr.link("add", ifname="pa", kind="veth", peer={"ifname": "pb"})
            ipr.link("add", ifname="pbr", kind="bridge")
            pa = ipr.link_lookup(ifname="pa")[0]
            ipr.link("set", index=pa, master=ipr.link_lookup(ifname="pbr")[0], state="up")
            found["veth_bridge"] = True
        except Exception as exc:
            why["veth_bridge"] = describe(exc, "a veth pair into a bridge")
            pa = ipr.link_lookup(ifname="lo")[0]
        for kind, opts in (
            ("netem", {"delay": 1000}),
            ("tbf", {"rate": 125_000, "burst": 3028, "latency": 50_000}),
        ):
            try:
                ipr.tc("add", kind=kind, index=pa, handle=0x10000, **opts)
                ipr.tc("del", index=pa, parent=TC_H_ROOT)
                found[kind] = True
            except NetlinkError as exc:
                # The kernel answers ENOENT for a qdisc kind it does not know.
                why[kind] = (
                    f"the kernel does not know the {kind} qdisc (module sch_{kind} not built "
                    "or not loadable)"
                    if exc.code == errno.ENOENT
                    else describe(exc, f"a {kind} qdisc")
                )
            except Exception as exc:
                why[kind] = describe(exc, f"a {kind} qdisc")
        try:
            _nft(
                name,
                f"table bridge {PROBE_TABLE} {{\n chain f {{\n type filter hook forward "
                "priority 0; policy accept;\n }\n}\n",
            )
            found["nft_bridge"] = True
            _nft(name, f"add rule bridge {PROBE_TABLE} f numgen random mod 100 < 50 drop")
            found["numgen"] = True
        except Exception as exc:
            key = "numgen" if found.get("nft_bridge") else "nft_bridge"
            why[key] = describe(
                exc, "an nftables " + ("numgen rule" if key == "numgen" else "bridge table")
            )
    finally:
        ipr.close()
        if name in netns.listnetns():
            netns.remove(name)
    radio, why_not = radio_support()
    if why_not:
        why["radio"] = why_not
    try:
        gc_thresh3 = hostlimits.current()["gc_thresh3"]
    except NetlabError as exc:
        gc_thresh3 = 0
        why["arp"] = str(exc)
    return Capabilities(
        root=True,
        gc_thresh3=gc_thresh3,
        netns=found.get("netns", False),
        veth_bridge=found.get("veth_bridge", False),
        nft_bridge=found.get("nft_bridge", False),
        numgen=found.get("numgen", False),
        netem=found.get("netem", False),
        tbf=found.get("tbf", False),
        radio=radio,
        why=why,
    )


def radio_support(
    proc: Path = Path("/proc"), sys_class: Path = Path("/sys/class")
) -> tuple[bool, str]:
    """Whether radio labs can run here, and if not why (the kernel, then the tools)."""
    if not hwsim.loaded():
        if not (sys_class / "ieee80211").exists() and not (proc / "modules").exists():
            return False, (
                "no mac80211_hwsim: this kernel has no wireless stack loaded and cannot load "
                "modules (no /proc/modules); the radio tier boots a kernel that has them in a "
                "VM (`make test-radio`)"
            )
        return False, (
            "no mac80211_hwsim loaded: `modprobe mac80211_hwsim radios=0` (each radio lab "
            "makes its own radios)"
        )
    missing = [tool for tool in ("iw", "wpa_supplicant") if shutil.which(tool) is None]
    if missing:
        return False, f"{' and '.join(missing)} not found: apt-get install iw wpasupplicant"
    return True, ""


@functools.cache
def capabilities() -> Capabilities:
    """The probe's result, run once per process."""
    return probe()


def report(caps: Capabilities) -> list[tuple[str, bool, str]]:
    """(capability, present, what follows) rows for `netlab doctor`."""
    vm = "the VM tier (`make test-netem`) has it"
    rows = [
        (
            "root",
            caps.root,
            "can create labs" if caps.root else "run netlab as root (sudo)",
        ),
        (
            "network namespaces",
            caps.netns,
            "one namespace per robot" if caps.netns else "no labs on this machine",
        ),
        (
            "veth + bridge",
            caps.veth_bridge,
            "robots share the medium bridge" if caps.veth_bridge else "no medium: no labs",
        ),
        (
            "nftables bridge family",
            caps.nft_bridge,
            "partitions, ranges and per-pair links"
            if caps.nft_bridge
            else "no medium rules: no labs (apt-get install nftables; CONFIG_NF_TABLES_BRIDGE)",
        ),
        (
            "nftables numgen",
            caps.numgen,
            "per-pair loss; link loss without netem"
            if caps.numgen
            else "no per-pair loss (module nft_numgen)",
        ),
        (
            "tc netem (sch_netem)",
            caps.netem,
            "delay, jitter, loss, duplicate, reorder, corrupt, rate on robot links"
            if caps.netem
            else "netlab shape refuses delay, jitter, duplicate, reorder and corrupt here; "
            "loss goes through nftables, rate through tbf. For them: `modprobe sch_netem`, or a "
            f"kernel with it; {vm}",
        ),
        (
            "tc tbf (sch_tbf)",
            caps.tbf,
            "rate limits without netem" if caps.tbf else "no rate limit unless netem is present",
        ),
        (
            "802.11 radios (hwsim)",
            caps.radio,
            "radio labs (medium radio): a radio per robot, sdfrd joins the fleet's WiFi"
            if caps.radio
            else "no radio labs here (see radio: below); the VM tier (`make test-radio`) has them",
        ),
    ]
    if caps.docker is not None:
        rows.append(
            (
                "docker + robot image",
                caps.docker,
                "robots as containers (--runtime docker)"
                if caps.docker
                else "no container robots (`make image` installs Docker and builds the image)",
            )
        )
    if caps.gc_thresh3:
        rows.append(
            (
                "ARP table (host-wide)",
                True,
                f"gc_thresh3 {caps.gc_thresh3}: full mesh of up to "
                f"{hostlimits.max_mesh(caps.gc_thresh3)} robots; bigger labs raise it until "
                "the last lab goes down",
            )
        )
    return rows


def format_report(caps: Capabilities) -> str:
    rows = report(caps)
    width = max(len(name) for name, _, _ in rows)
    lines = [f"{'capability'.ljust(width)}  ok   consequence"]
    for name, ok, consequence in rows:
        lines.append(f"{name.ljust(width)}  {'yes' if ok else 'NO ':<3}  {consequence}")
    if caps.why:
        lines.append("")
        lines += [f"{key}: {reason}" for key, reason in sorted(caps.why.items())]
    return "\n".join(lines)
