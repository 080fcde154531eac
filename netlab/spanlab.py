"""A lab spread over hosts, driven from here: one `netlab.agent` per host over ssh.

`SpanLab` spreads the robots over the hosts (given per host, or in turn), numbers them across
the lab (addresses and MACs never collide between hosts), brings up each host's share with a
`netlab.vxlan.Span` joining the media, tells every host where every other host's robots are,
and sends each change of the medium (moves, partitions, the merge) to every host, so that each
host judges the frames it receives by the same map.  Questions about a robot go to its host.

Each host's share is a lab of its own name (``<lab><i>``... as given by `part_names`): on
hosts simulated on one machine (`netlab.hostsim`) the shares' namespaces share one list.

Clean-up: `down` asks every host to take its share down; a host that cannot be reached is
named in the error after the others are down.  An agent also takes its share down when its
ssh session ends (the controller died, or the connection dropped).
"""

from __future__ import annotations

import contextlib
import json
import subprocess
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any

from netlab import naming
from netlab.errors import NetlabError
from netlab.hosts import HostError, Ssh
from netlab.ranges import Pos
from netlab.vxlan import DEFAULT_PORT, vni_for


class Part:
    """One host's agent: requests in, answers out, over the ssh session."""

    def __init__(self, ssh: Ssh, env: Mapping[str, str] | None = None) -> None:
        self.ssh = ssh
        prefix = ["env", *(f"{k}={v}" for k, v in (env or {}).items())] if env else []
        argv = ssh.argv([*prefix, ssh.python, "-m", "netlab.agent"])
        self.proc = subprocess.Popen(
            argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )

    def call(self, op: str, **kw: Any) -> Any:
        """One request; its result, or HostError naming the host and what it said."""
        assert self.proc.stdin is not None and self.proc.stdout is not None
        try:
            self.proc.stdin.write(json.dumps({"op": op, **kw}) + "\n")
            self.proc.stdin.flush()
        except (BrokenPipeError, OSError):
            raise HostError(f"host {self.ssh.destination}: {op}: {self._ended()}") from None
        line = self.proc.stdout.readline()
        if not line:
            raise HostError(f"host {self.ssh.destination}: {op}: {self._ended()}")
        answer = json.loads(line)
        if not answer.get("ok"):
            raise HostError(f"host {self.ssh.destination}: {answer.get('error')}")
        return answer.get("result")

    def _ended(self) -> str:
        try:
            code: int | None = self.proc.wait(5)  # its stdout closed: it is ending
        except subprocess.TimeoutExpired:
            code = None
        err = self.proc.stderr.read() if self.proc.stderr and code is not None else ""
        said = err.strip().splitlines()[-1] if err.strip() else "no word"
        if code == 255:
            return f"cannot be reached over ssh ({said})"
        return f"its agent ended ({said})"

    def close(self, timeout: float = 60.0) -> None:
        if self.proc.stdin is not None:
            with contextlib.suppress(OSError):
                self.proc.stdin.close()
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)


@dataclass(slots=True)
class SpanLab:
    """`robots` spread over `hosts` (ssh destinations with their underlay addresses)."""

    name: str
    hosts: Sequence[tuple[Ssh, str]]  # (how to reach it, its underlay address)
    robots: Mapping[str, str]  # robot -> host destination
    seed: int = 7
    fleet: int = 3
    radius: float = 20.0
    positions: Mapping[str, Pos] = field(default_factory=dict)
    workdir: str = "/tmp"
    port: int = DEFAULT_PORT
    env: Mapping[str, str] = field(default_factory=dict)
    parts: dict[str, Part] = field(default_factory=dict)
    index: dict[str, int] = field(default_factory=dict)
    macs: dict[str, str] = field(default_factory=dict)

    def part_names(self) -> dict[str, str]:
        """Each host's share's own lab name: the lab's, then the host's number (base 36)."""
        base = self.name[:7]
        return {ssh.destination: f"{base}{naming.b36(i)}" for i, (ssh, _) in enumerate(self.hosts)}

    def host_of(self, robot: str) -> Part:
        try:
            return self.parts[self.robots[robot]]
        except KeyError:
            raise NetlabError(f"lab {self.name} has no robot {robot!r}") from None

    def __enter__(self) -> SpanLab:
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
        naming.check_lab_name(self.name)
        dests = [ssh.destination for ssh, _ in self.hosts]
        unknown = sorted({h for h in self.robots.values() if h not in dests})
        if unknown:
            raise NetlabError(f"lab {self.name}: robots on unknown hosts {', '.join(unknown)}")
        addrs = [addr for _, addr in self.hosts]
        names = self.part_names()
        for i, name in enumerate(self.robots):
            self.index[name] = i
        span = {"lab": self.name, "vni": vni_for(self.name), "hosts": addrs, "port": self.port}
        for ssh, addr in self.hosts:
            part = Part(ssh, self.env)
            self.parts[ssh.destination] = part
            workdir = f"{self.workdir}/{names[ssh.destination]}"
            here = {**span, "local": addr}
            part.call("up", name=names[ssh.destination], seed=self.seed, fleet=self.fleet,
                      radius=self.radius, workdir=workdir, span=here)  # fmt: skip
        for robot, host in self.robots.items():
            pos = list(self.positions.get(robot, (0.0, 0.0)))
            self.macs[robot] = self.parts[host].call(
                "add_robot", name=robot, index=self.index[robot], pos=pos
            )
        for robot, host in self.robots.items():
            pos = list(self.positions.get(robot, (0.0, 0.0)))
            for dest, part in self.parts.items():
                if dest != host:
                    part.call("add_remote", name=robot, mac=self.macs[robot], pos=pos)

    def start_all(self, timeout: float = 60.0, **options: Any) -> None:
        for dest, part in self.parts.items():
            mine = [r for r, h in self.robots.items() if h == dest]
            part.call("start_all", robots=mine, timeout=timeout, options=options)

    def _everywhere(self, op: str, **kw: Any) -> None:
        for part in self.parts.values():
            part.call(op, **kw)

    def move(self, robot: str, pos: Pos) -> None:
        self.host_of(robot)
        self._everywhere("move", robot=robot, pos=list(pos))

    def partition(self, groups: Sequence[Sequence[str]]) -> None:
        self._everywhere("partition", groups=[list(g) for g in groups])

    def merge(self) -> None:
        self._everywhere("merge")

    def neighbors(self, robot: str) -> set[str]:
        return set(self.host_of(robot).call("neighbors", robot=robot))

    def down(self) -> None:
        """Every host's share down; HostError naming the hosts that could not be reached."""
        failed = []
        for dest, part in self.parts.items():
            try:
                if part.proc.poll() is not None:
                    raise HostError(f"host {dest}: down: {part._ended()}")
                part.call("down")
            except HostError as exc:
                failed.append(str(exc))
            finally:
                part.close()
                part.ssh.close()
        self.parts.clear()
        if failed:
            raise HostError("; ".join(failed))
