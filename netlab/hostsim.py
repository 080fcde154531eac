"""Hosts on one machine: network namespaces that a controller reaches over SSH like machines.

A lab across hosts is driven over SSH (`netlab.hosts`).  To test that for real on one
machine, each "host" here is a network namespace ``nl-<name>-h<i>`` with its own address on a
shared underlay (a bridge in ``nl-<name>-ul``) and its own OpenSSH server listening there, with
a host key and an authorized client key made for the occasion.  The controller (this
process, in the initial namespace) reaches the underlay through one veth, ``nl<name>ul`` with
the underlay's last address, and runs plain ``ssh`` with the `ssh_config` file written here:
the same program, keys and configuration path a team's real hosts would use.

What is shared with the machine (unlike real hosts): the filesystem, the process table, the
namespace names and the clock.  A lab across these hosts must therefore name each host's
kernel objects apart (it does, by host), and it measures no real clock offset.

Everything made is named after `name` (a lab name: 1-8 of a-z, 0-9), so that `netlab down
NAME`'s sweep finds the namespaces (and the sshd inside them) after a crash; `down` also
removes the controller's veth, the one object made in the initial namespace.
"""

from __future__ import annotations

import contextlib
import hashlib
import ipaddress
import os
import shlex
import shutil
import signal
import subprocess
import tempfile
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

from netlab import cleanup, hostlimits, kernel, naming
from netlab.errors import NetlabError

SSHD = "/usr/sbin/sshd"
#: The underlays' /24s are taken from here: a block of 10.0.0.0/8 unlikely to be routed.
UNDERLAYS = ipaddress.IPv4Network("10.254.0.0/16")
UL_BRIDGE = "ul0"
UL_IFACE = "ul0"


@dataclass(frozen=True, slots=True)
class SimHost:
    """One host: its SSH alias (in `SimHosts.ssh_config`), namespace and underlay address."""

    alias: str
    ns: str
    address: str


def routed() -> list[ipaddress.IPv4Network]:
    """The IPv4 networks the initial namespace routes now (its own and other labs')."""
    out = subprocess.run(["ip", "-4", "route", "show", "table", "all"], capture_output=True,
                         text=True, check=False).stdout  # fmt: skip
    nets = []
    for line in out.splitlines():
        word = line.split()[0] if line.split() else ""
        if word in ("broadcast", "local", "unicast"):
            word = line.split()[1]
        with contextlib.suppress(ValueError):
            nets.append(ipaddress.IPv4Network(word if word != "default" else "0.0.0.0/0"))
    return [n for n in nets if n.prefixlen > 0]


def free_subnet(name: str, taken: Sequence[ipaddress.IPv4Network]) -> ipaddress.IPv4Network:
    """A /24 of UNDERLAYS that overlaps none of `taken`, the first tried derived from `name`
    (two simulations side by side pick apart)."""
    subnets = list(UNDERLAYS.subnets(new_prefix=24))
    start = int(hashlib.sha256(name.encode()).hexdigest(), 16) % len(subnets)
    for i in range(len(subnets)):
        net = subnets[(start + i) % len(subnets)]
        if not any(net.overlaps(t) for t in taken):
            return net
    raise NetlabError(f"simulated hosts: every /24 of {UNDERLAYS} is routed here already")


def needs() -> list[str]:
    """What this machine lacks to simulate hosts, each with how to get it; [] when ready."""
    out = []
    if os.geteuid() != 0:
        out.append("root (namespaces and veths)")
    if not Path(SSHD).exists():
        out.append(f"{SSHD} (apt-get install openssh-server)")
    for tool, pkg in (("ssh", "openssh-client"), ("ssh-keygen", "openssh-client")):
        if shutil.which(tool) is None:
            out.append(f"{tool} (apt-get install {pkg})")
    return out


class SimHosts:
    """`count` hosts named ``h1``..``hN`` (their SSH aliases), each with sshd; a context
    manager that removes everything it made, also after a failed `up`."""

    def __init__(
        self,
        name: str,
        count: int,
        workdir: Path,
        subnet: ipaddress.IPv4Network | None = None,
        robots: int = 0,
    ) -> None:
        self.name = naming.check_lab_name(name)
        #: Robots the labs on these hosts will hold in all: the hosts share this machine's
        #: one ARP table, whose limits their labs cannot raise from their own namespaces
        #: (`netlab.hostlimits`), so `up` raises them for that many (and `down` restores
        #: them once no lab is left).
        self.robots = robots
        if not 1 <= count <= 200:
            raise NetlabError(f"simulated hosts: 1 to 200 hosts, got {count}")
        self.count = count
        self.workdir = workdir
        subnet = subnet if subnet is not None else free_subnet(name, routed())
        self.subnet = subnet
        addrs = list(subnet.hosts())
        self.hosts = [
            SimHost(f"h{i}", f"{naming.NS_PREFIX}{name}-h{i}", str(addrs[i - 1]))
            for i in range(1, count + 1)
        ]
        self.controller_address = str(addrs[-1])
        self.underlay_ns = f"{naming.NS_PREFIX}{name}-ul"
        self.veth = f"nl{name}ul"
        self.ssh_config = workdir / "ssh_config"
        self.identity = workdir / "id_ed25519"
        self._sshd: dict[str, subprocess.Popen[bytes]] = {}
        #: Where ssh's shared connections to these hosts live (short: a socket path is at
        #: most 107 bytes), apart from any other simulation's that had the same addresses.
        self.control_dir = Path(tempfile.mkdtemp(prefix="nl-ssh-"))

    # -- up and down ---------------------------------------------------------------------

    def __enter__(self) -> SimHosts:
        try:
            self.up()
        except BaseException:
            self.down()
            raise
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.down()

    def up(self) -> None:
        missing = needs()
        if missing:
            raise NetlabError(f"cannot simulate hosts here: needs {', '.join(missing)}")
        self.workdir.mkdir(parents=True, exist_ok=True)
        if self.robots:
            hostlimits.ensure(hostlimits.mesh_entries(self.robots))
        self._keys()
        self._underlay()
        for host in self.hosts:
            self._host(host)
        self._write_ssh_config()
        for host in self.hosts:
            self._start_sshd(host)
        for host in self.hosts:
            self._wait_listening(host)

    def down(self) -> None:
        """Stop every sshd, remove the namespaces and the controller's veth (idempotent)."""
        for proc in self._sshd.values():
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGTERM)
        for proc in self._sshd.values():
            try:
                proc.wait(5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)
        self._sshd.clear()
        # What the sessions left running on the hosts (an agent, sshd's per-connection
        # processes): killed, so that the controller's shared connections end now.
        inodes = {i for i in (kernel.ns_inode(h.ns) for h in self.hosts) if i is not None}
        cleanup.kill_inside(inodes)
        for sock in self.control_dir.glob("*"):
            sock.unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            self.control_dir.rmdir()
        subprocess.run(["ip", "link", "del", self.veth], capture_output=True, check=False)
        for ns in [h.ns for h in self.hosts] + [self.underlay_ns]:
            kernel.remove_ns(ns)
        if self.robots:
            hostlimits.restore_if_last()

    def kill_sshd(self, alias: str) -> None:
        """Kill one host's sshd (a host that died, as far as the controller can tell)."""
        proc = self._sshd.pop(alias)
        proc.kill()
        proc.wait(5)

    # -- the pieces ------------------------------------------------------------------------

    def _run(self, argv: Sequence[str], doing: str) -> str:
        return kernel.run_argv(argv, f"simulated hosts: {doing}")

    def _keys(self) -> None:
        for key in (self.identity, self.workdir / "host_ed25519"):
            if not key.exists():
                self._run(
                    ["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-C", f"netlab-{self.name}",
                     "-f", str(key)],
                    f"making the key {key}",
                )  # fmt: skip
        pub = (self.workdir / "host_ed25519.pub").read_text().split()
        known = [f"{h.address} {pub[0]} {pub[1]}" for h in self.hosts]
        (self.workdir / "known_hosts").write_text("\n".join(known) + "\n")
        shutil.copyfile(self.identity.with_suffix(".pub"), self.workdir / "authorized_keys")

    def _underlay(self) -> None:
        ns = self.underlay_ns
        kernel.create_ns(ns).close()
        prefix = self.subnet.prefixlen
        self._run(["ip", "-n", ns, "link", "add", UL_BRIDGE, "type", "bridge"], "the underlay")
        self._run(["ip", "-n", ns, "link", "set", UL_BRIDGE, "up"], "the underlay")
        self._run(
            ["ip", "link", "add", self.veth, "type", "veth", "peer", "name", "ctl",
             "netns", ns],
            "the controller's veth",
        )  # fmt: skip
        self._run(["ip", "-n", ns, "link", "set", "ctl", "master", UL_BRIDGE, "up"], "underlay")
        self._run(
            ["ip", "addr", "add", f"{self.controller_address}/{prefix}", "dev", self.veth],
            "the controller's address",
        )
        self._run(["ip", "link", "set", self.veth, "up"], "the controller's veth")

    def _host(self, host: SimHost) -> None:
        kernel.create_ns(host.ns).close()
        port = f"p{host.alias}"
        self._run(
            ["ip", "-n", self.underlay_ns, "link", "add", port, "type", "veth", "peer", "name",
             UL_IFACE, "netns", host.ns],
            f"{host.alias}'s underlay link",
        )  # fmt: skip
        self._run(
            ["ip", "-n", self.underlay_ns, "link", "set", port, "master", UL_BRIDGE, "up"],
            f"{host.alias}'s underlay port",
        )
        for argv in (
            ["ip", "-n", host.ns, "addr", "add", f"{host.address}/{self.subnet.prefixlen}",
             "dev", UL_IFACE],
            ["ip", "-n", host.ns, "link", "set", UL_IFACE, "up"],
            ["ip", "-n", host.ns, "link", "set", "lo", "up"],
        ):  # fmt: skip
            self._run(argv, f"{host.alias}'s underlay address")

    def _sshd_config(self, host: SimHost) -> Path:
        path = self.workdir / f"sshd_{host.alias}.conf"
        lines = [
            f"ListenAddress {host.address}",
            "Port 22",
            f"HostKey {self.workdir / 'host_ed25519'}",
            f"AuthorizedKeysFile {self.workdir / 'authorized_keys'}",
            f"PidFile {self.workdir / f'sshd_{host.alias}.pid'}",
            "PermitRootLogin prohibit-password",
            "PasswordAuthentication no",
            "KbdInteractiveAuthentication no",
            "UsePAM no",
            "StrictModes no",
            "MaxSessions 64",
            # A session whose controller vanished with the underlay ends within 15 s.
            "ClientAliveInterval 5",
            "ClientAliveCountMax 3",
            "MaxStartups 64:30:128",
            "Subsystem sftp internal-sftp",
            "AcceptEnv LANG LC_*",
        ]
        path.write_text("\n".join(lines) + "\n")
        return path

    def _start_sshd(self, host: SimHost) -> None:
        config = self._sshd_config(host)
        log = self.workdir / f"sshd_{host.alias}.log"
        Path("/run/sshd").mkdir(mode=0o755, exist_ok=True)  # its privilege separation dir
        # nsenter, not `ip netns exec`: only the network namespace changes, so that what a
        # session mounts (the namespaces it makes, under /run/netns) is seen machine-wide.
        argv = ["nsenter", f"--net=/run/netns/{host.ns}", SSHD, "-D", "-e", "-f", str(config)]
        with log.open("ab") as out:
            self._sshd[host.alias] = subprocess.Popen(
                argv, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL
            )

    def _wait_listening(self, host: SimHost, timeout: float = 20.0) -> None:
        deadline = time.monotonic() + timeout
        proc = self._sshd[host.alias]
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                log = (self.workdir / f"sshd_{host.alias}.log").read_text().strip()
                raise NetlabError(f"simulated host {host.alias}: sshd ended: {log[-400:]}")
            listening = kernel.run_in_ns(host.ns, ["ss", "-Htln"], "sshd's socket")
            if f"{host.address}:22 " in listening:
                return
            time.sleep(0.05)
        raise NetlabError(f"simulated host {host.alias}: sshd not listening in {timeout:.0f} s")

    def _write_ssh_config(self) -> None:
        blocks = []
        for host in self.hosts:
            blocks += [
                f"Host {host.alias}",
                f"\tHostName {host.address}",
                "\tUser root",
                f"\tIdentityFile {self.identity}",
                "\tIdentitiesOnly yes",
                f"\tUserKnownHostsFile {self.workdir / 'known_hosts'}",
                "\tStrictHostKeyChecking yes",
                "\tBatchMode yes",
                "\tConnectTimeout 5",
                "",
            ]
        self.ssh_config.write_text("\n".join(blocks))

    def ssh_argv(self, alias: str, argv: Sequence[str]) -> list[str]:
        """``ssh -F <config> ALIAS -- ARGV``: how the controller runs a command on a host
        (each argument quoted for the remote shell, as ssh joins them into one line)."""
        return ["ssh", "-F", str(self.ssh_config), alias, "--", shlex.join(argv)]

    def aliases(self) -> Iterator[str]:
        return (h.alias for h in self.hosts)
