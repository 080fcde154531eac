"""A robot of the side-by-side bench done with Avahi (Debian's avahi-daemon and avahi-utils, the
mDNS / DNS-SD daemon of every Linux robot) instead of SDfR.

Run inside a robot's namespace (`ip netns exec` gives it a mount namespace of its own), as
Avahi's users run it: one avahi-daemon a robot, with its defaults but for its host name (the
robot's: the robots share one kernel's host name) and IPv4 only; its own D-Bus system bus (a
`dbus-daemon` of the robot's), since the robots cannot share one; and Avahi's own tools on that
bus.  Each service is an `avahi-publish -s` process (its TXT record the service's attributes),
unpublished by ending it (the daemon withdraws the records with a goodbye); `avahi-browse -r -p
-k` lists the others': a service is *listed* once resolved (a ``=`` line: its SRV, TXT and
address known), gone on its ``-`` line.  avahi-daemon keeps its pid at a fixed path, so the
robot's own folders are bind-mounted over /run/avahi-daemon and /etc/avahi/services (in the
node's mount namespace only).

The daemon and the tools end with the node (PR_SET_PDEATHSIG), so a kill -9 of the node is a
robot's silent death: no goodbye is sent, and the others keep its services for the records'
TTL (Avahi's: 75 minutes for PTR and TXT).  Its command line, churn, signals and event log are
`bench.peer_node`'s; the robot's files (D-Bus and Avahi configuration, sockets) are in
``<events>.avahi/``.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes  # noqa: F401  (die_with_parent's: imported before any fork, not in the child)
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from bench.peer_node import PeerNode, arguments, attributes
from sdfr.host.procfs import die_with_parent

TYPE = "_sdfrbench._tcp"
PORT_BASE = 9000
READY_S = 30.0  # how long the daemon may take to answer on its bus
#: What a robot needs installed (scripts/avahi-setup.sh).
PROGRAMS = ("avahi-daemon", "avahi-publish", "avahi-browse", "dbus-daemon")

DBUS_CONF = """<!DOCTYPE busconfig PUBLIC "-//freedesktop//DTD D-Bus Bus Configuration 1.0//EN"
 "http://www.freedesktop.org/standards/dbus/1.0/busconfig.dtd">
<busconfig>
  <type>system</type>
  <listen>unix:path={socket}</listen>
  <auth>EXTERNAL</auth>
  <policy context="default">
    <allow user="*"/>
    <allow own="*"/>
    <allow send_destination="*"/>
    <allow receive_sender="*"/>
  </policy>
</busconfig>
"""

AVAHI_CONF = """[server]
host-name={robot}
use-ipv4=yes
use-ipv6=no
enable-dbus=yes

[wide-area]
enable-wide-area=no

[publish]
publish-hinfo=no
publish-workstation=no
"""


def instance(robot: str, sid: str) -> str:
    return f"{robot}--{sid}"


def owner(name: str) -> tuple[str, str] | None:
    """(robot, service id) of an instance name of this bench, else None."""
    robot, sep, sid = name.partition("--")
    return (robot, sid) if sep and robot and sid else None


def browse_line(line: str) -> tuple[str, tuple[str, str]] | None:
    """("=" resolved or "-" removed, (robot, sid)) of a line of `avahi-browse -p`, else None
    (a "+" line: found, not yet resolved)."""
    fields = line.rstrip("\n").split(";")
    if len(fields) < 6 or fields[0] not in ("=", "-") or fields[4] != TYPE:
        return None
    who = owner(unescape(fields[3]))
    return (fields[0], who) if who is not None else None


def unescape(name: str) -> str:
    """avahi-browse -p writes some characters of a name as a backslash and three digits."""
    out, i = [], 0
    while i < len(name):
        if name[i] == "\\" and name[i + 1 : i + 4].isdigit():
            out.append(chr(int(name[i + 1 : i + 4])))
            i += 4
        else:
            out.append(name[i])
            i += 1
    return "".join(out)


def txt(attrs: dict[str, str]) -> list[str]:
    return [f"{k}={v}" for k, v in attrs.items()]


class Node(PeerNode):
    def __init__(self, args: Any, events: Any) -> None:
        super().__init__(args, events)
        self.home = Path(f"{args.events}.avahi")
        self.env = dict(os.environ)
        self.procs: list[subprocess.Popen[bytes]] = []

    def start(self, argv: list[str], log: str, **kw: Any) -> subprocess.Popen[bytes]:
        with open(self.home / log, "ab") as out:
            proc = subprocess.Popen(argv, env=self.env, stdin=subprocess.DEVNULL, stdout=out,
                                    stderr=out, preexec_fn=die_with_parent, **kw)  # fmt: skip
        self.procs.append(proc)
        return proc

    def set_up(self) -> None:
        """The robot's own bus and daemon, and their folders over the fixed paths."""
        for need in PROGRAMS:
            if shutil.which(need) is None:
                raise SystemExit(f"avahi node: no {need} here (bash scripts/avahi-setup.sh)")
        self.home.mkdir(parents=True, exist_ok=True)
        for sub in ("run", "services"):
            (self.home / sub).mkdir(exist_ok=True)
        for folder, over in (("run", "/run/avahi-daemon"), ("services", "/etc/avahi/services")):
            Path(over).mkdir(parents=True, exist_ok=True)
            subprocess.run(["mount", "--bind", str(self.home / folder), over], check=True)
        bus = self.home / "bus.sock"
        bus.unlink(missing_ok=True)
        (self.home / "dbus.conf").write_text(DBUS_CONF.format(socket=bus))
        (self.home / "avahi-daemon.conf").write_text(AVAHI_CONF.format(robot=self.robot))
        self.env["DBUS_SYSTEM_BUS_ADDRESS"] = f"unix:path={bus}"
        self.start(["dbus-daemon", f"--config-file={self.home / 'dbus.conf'}", "--nofork",
                    "--nopidfile"], "dbus.log")  # fmt: skip
        deadline = time.monotonic() + READY_S
        while not bus.exists():
            if time.monotonic() > deadline:
                raise SystemExit(f"avahi node: no D-Bus at {bus} within {READY_S:g} s")
            time.sleep(0.05)
        self.start(["avahi-daemon", "-f", str(self.home / "avahi-daemon.conf"), "--no-drop-root",
                    "--no-chroot", "--no-rlimits"], "avahi-daemon.log")  # fmt: skip
        while subprocess.run(["avahi-browse", "-t", "-p", TYPE], env=self.env,
                             capture_output=True).returncode != 0:  # fmt: skip
            if time.monotonic() > deadline:
                raise SystemExit(f"avahi node: avahi-daemon not on its bus within {READY_S:g} s")
            time.sleep(0.1)

    async def register(self, index: int, sid: str) -> Any:
        attrs = attributes(self.robot, index)
        argv = ["avahi-publish", "-s", instance(self.robot, sid), TYPE, str(PORT_BASE + index),
                *txt(attrs)]  # fmt: skip
        return self.start(argv, "publish.log")

    async def unregister(self, handle: Any) -> None:
        proc: subprocess.Popen[bytes] = handle
        proc.terminate()  # (its entry group freed: the daemon says goodbye)
        await asyncio.get_running_loop().run_in_executor(None, proc.wait)
        self.procs.remove(proc)

    async def leave(self) -> None:
        """Withdraw every service, one publisher at a time (the daemon says goodbye for each
        and keeps running, as a robot's avahi-daemon would)."""
        t0 = time.perf_counter()
        for sid in list(self.mine):
            await self.unregister(self.mine.pop(sid))
        self.left((time.perf_counter() - t0) * 1000)

    async def watch(self) -> None:
        browse = await asyncio.create_subprocess_exec(
            "avahi-browse", "-r", "-p", "-k", TYPE, env=self.env, stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, preexec_fn=die_with_parent,
        )  # fmt: skip
        assert browse.stdout is not None
        while line := await browse.stdout.readline():
            got = browse_line(line.decode(errors="replace"))
            if got is None or got[1][0] == self.robot:
                continue
            (self.seen if got[0] == "=" else self.gone)(got[1])

    def stop_all(self) -> None:
        for proc in reversed(self.procs):  # (the publishers, then the daemon, then its bus)
            with contextlib.suppress(ProcessLookupError):
                proc.terminate()
        for proc in reversed(self.procs):
            try:
                proc.wait(5)
            except subprocess.TimeoutExpired:
                proc.kill()

    async def run(self) -> None:
        self.set_up()
        try:
            self.spawn(self.watch())
            await self.serve()
        finally:
            self.stop_all()


def main(argv: list[str] | None = None) -> int:
    args = arguments(__doc__ or "").parse_args(argv)
    with open(args.events, "w", buffering=1) as events:
        try:
            asyncio.run(Node(args, events).run())
        except SystemExit as exc:
            print(exc, file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
