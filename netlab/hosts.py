"""The hosts of a lab across machines, driven over SSH.

netlab runs commands on each host with OpenSSH (``ssh``, the user's keys and
``~/.ssh/config``, or the file given), one shared connection per host (ControlMaster), in batch
mode (never a password prompt).  `look` checks what a host must have before anything is made
there: that it answers, runs as root, has the same netlab (sdfr-robots) version as this
controller, the tools a lab needs and VXLAN in its kernel; and it measures the host's clock
against this one (the offset, and the bound the round trip puts on it).

`netlab doctor --hosts H1,H2,...` prints the same, one host per line, and fails when any host
cannot take part.
"""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from netlab.errors import NetlabError

#: Run on a host by its interpreter: what it has, as one JSON line.
PROBE = r"""
import glob, json, os, shutil, time
out = {"uid": os.geteuid(), "time": time.time(), "version": None}
try:
    import sdfr
    out["version"] = sdfr.__version__
except Exception as exc:
    out["import_error"] = f"{type(exc).__name__}: {exc}"
out["missing"] = [t for t in ("ip", "nft", "bridge", "tcpdump") if shutil.which(t) is None]
# Built in or loaded (/sys/module), or a module `ip link add ... type vxlan` would load.
release = os.uname().release
out["vxlan"] = os.path.exists("/sys/module/vxlan") or bool(
    glob.glob(f"/lib/modules/{release}/kernel/drivers/net/vxlan*"))
print(json.dumps(out))
"""


#: An ssh destination: an alias, host, user@host or [v6 address]; never an option ("-o...").
DESTINATION_RE = re.compile(r"[A-Za-z0-9_\[][\w.@:%\[\]-]{0,252}")


class HostError(NetlabError):
    """A host that cannot be reached, or refuses what was asked."""


@dataclass(slots=True)
class Ssh:
    """Commands on one host over ssh: `destination` as ssh takes it (an alias of the ssh
    configuration, ``user@address``), `python` the interpreter with netlab there."""

    destination: str
    ssh_config: Path | None = None
    python: str = "python3"
    control_dir: Path = field(default_factory=lambda: Path(tempfile.gettempdir()))
    connect_timeout: int = 5

    def __post_init__(self) -> None:
        if not DESTINATION_RE.fullmatch(self.destination):
            raise HostError(
                f"{self.destination!r} is not an ssh destination (an alias of the ssh "
                "configuration, or user@address)"
            )

    def argv(self, argv: Sequence[str]) -> list[str]:
        """The ssh command line that runs `argv` on the host (quoted for its shell)."""
        opts = ["-F", str(self.ssh_config)] if self.ssh_config is not None else []
        opts += [
            "-o", "BatchMode=yes",
            "-o", f"ConnectTimeout={self.connect_timeout}",
            "-o", "ControlMaster=auto",
            "-o", f"ControlPath={self.control_dir}/netlab-ssh-%C",
            "-o", "ControlPersist=60",
        ]  # fmt: skip
        return ["ssh", *opts, self.destination, "--", shlex.join(argv)]

    def run(
        self, argv: Sequence[str], doing: str, timeout: float = 60.0, stdin: str | None = None
    ) -> str:
        """Run `argv` on the host; its stdout, or HostError saying which host, what was
        being done and what ssh or the command said."""
        try:
            done = subprocess.run(
                self.argv(argv), input=stdin, capture_output=True, text=True, timeout=timeout,
                stdin=None if stdin is not None else subprocess.DEVNULL, check=False,
            )  # fmt: skip
        except subprocess.TimeoutExpired:
            raise HostError(
                f"host {self.destination}: {doing}: no answer in {timeout:.0f} s"
            ) from None
        except OSError as exc:
            raise HostError(f"host {self.destination}: cannot run ssh: {exc}") from None
        if done.returncode == 255:  # ssh's own failure: the host was not reached
            said = _last_line(done.stderr) or "ssh failed"
            raise HostError(f"host {self.destination} cannot be reached over ssh: {said}")
        if done.returncode != 0:
            said = _last_line(done.stderr) or _last_line(done.stdout)
            raise HostError(
                f"host {self.destination}: {doing} failed (exit {done.returncode}): {said}"
            )
        return done.stdout

    def close(self) -> None:
        """End the shared connection, if one is open."""
        subprocess.run([*self.argv([])[:-2], "-O", "exit", self.destination], capture_output=True,
                       timeout=10, check=False)  # fmt: skip


def _last_line(text: str) -> str:
    lines = [line.strip() for line in text.strip().splitlines() if line.strip()]
    return lines[-1] if lines else ""


@dataclass(frozen=True, slots=True)
class HostLook:
    """What `look` found on a host: `problems` empty when it can take part in a lab."""

    destination: str
    problems: tuple[str, ...]
    version: str | None = None
    clock_offset: float | None = None  # host's clock minus this one's, seconds
    clock_bound: float | None = None  # half the round trip: the offset's uncertainty

    @property
    def ok(self) -> bool:
        return not self.problems

    def line(self) -> str:
        if self.clock_offset is not None and self.clock_bound is not None:
            clock = f"clock {self.clock_offset * 1e3:+.1f} ms (+-{self.clock_bound * 1e3:.1f})"
        else:
            clock = "clock not measured"
        if self.ok:
            return f"{self.destination}: ok: netlab {self.version}, root, VXLAN, {clock}"
        return f"{self.destination}: cannot take part: {'; '.join(self.problems)}"


def look(ssh: Ssh, version: str | None = None) -> HostLook:
    """Check one host (see the module doc); never raises for the host's faults."""
    from sdfr import __version__

    want = version or __version__
    t0 = time.time()
    try:
        out = ssh.run([ssh.python, "-c", PROBE], "looking at what it has", timeout=30)
    except HostError as exc:
        return HostLook(ssh.destination, (str(exc).removeprefix(f"host {ssh.destination} "),))
    t1 = time.time()
    try:
        found = json.loads(out.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return HostLook(ssh.destination, (f"{ssh.python} said something else: {out[-200:]!r}",))
    problems = []
    have = found.get("version")
    if have is None:
        why = found.get("import_error", "not importable")
        problems.append(f"no netlab for {ssh.python} ({why}): install sdfr-robots {want} there")
    elif have != want:
        problems.append(f"netlab {have} there, {want} here: run the same version everywhere")
    if found.get("uid") != 0:
        problems.append("not root there (namespaces, veths and nftables need root)")
    if found.get("missing"):
        problems.append(f"missing {', '.join(found['missing'])} (iproute2, nftables, tcpdump)")
    if not found.get("vxlan"):
        problems.append("no VXLAN in its kernel (CONFIG_VXLAN, or modprobe vxlan)")
    offset = float(found["time"]) - (t0 + t1) / 2
    return HostLook(ssh.destination, tuple(problems), have, offset, (t1 - t0) / 2)


def look_all(sshs: Sequence[Ssh]) -> list[HostLook]:
    return [look(s) for s in sshs]


def main_doctor(destinations: Sequence[str], ssh_config: Path | None, python: str) -> int:
    """`netlab doctor --hosts`: one line per host; 1 when any cannot take part."""
    sshs = [Ssh(d, ssh_config, python) for d in destinations]
    try:
        looks = look_all(sshs)
    finally:
        for s in sshs:
            s.close()
    for found in looks:
        print(found.line())
    bad = [f.destination for f in looks if not f.ok]
    if bad:
        print(f"netlab: {len(bad)} of {len(looks)} hosts cannot take part: {', '.join(bad)}",
              file=sys.stderr)  # fmt: skip
    return 1 if bad else 0
