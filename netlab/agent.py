"""A host's share of a lab across hosts, run over ssh: ``python -m netlab.agent``.

The controller (`netlab.spanlab`) starts one agent per host over its ssh session and talks
to it in JSON lines on the session's stdin and stdout: one request per line,
``{"op": NAME, ...arguments}``, one answer per line, ``{"ok": true, "result": ...}`` or
``{"ok": false, "error": "what went wrong"}`` (a `NetlabError`'s sentence; anything else
is named with its type).  The agent holds one `Lab` with a `Span` (its robots, the other
hosts' robots as remote ones) and takes it down when told ``down``, when its stdin closes
(the controller or the connection died) or on SIGTERM/SIGHUP.

Operations: ``up`` (name, seed, fleet, radius, workdir, span: vni, local, hosts, port),
``add_robot`` (name, index, pos), ``add_remote`` (name, mac, pos), ``start_all``
(robots, timeout, options), ``stop`` (robot), ``move`` (robot, pos), ``partition`` (groups),
``merge``, ``neighbors`` (robot: the robot ids its sdfrd lists), ``down``.
"""

from __future__ import annotations

import json
import os
import signal
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

from netlab.errors import NetlabError
from netlab.ranges import UnitDisc


class Agent:
    """The operations on this host's share of the lab (see the module doc)."""

    def __init__(self) -> None:
        from netlab.lab import Lab

        self.lab: Lab | None = None

    def _lab(self) -> Any:
        if self.lab is None:
            raise NetlabError("no lab here yet: `up` first")
        return self.lab

    def up(self, name: str, seed: int, fleet: int, radius: float, workdir: str,
           span: dict[str, Any]) -> str:  # fmt: skip
        from netlab.lab import Lab
        from netlab.vxlan import span_of

        if self.lab is not None:
            raise NetlabError(f"a lab {self.lab.name} is up here already")
        hosts = [str(h) for h in span["hosts"]]
        extra = {"port": int(span["port"])} if "port" in span else {}
        plan = span_of(str(span["lab"]), str(span["local"]), hosts, vni=int(span["vni"]), **extra)
        lab = Lab(name, seed=seed, fleet=fleet, range_model=UnitDisc(radius),
                  workdir=Path(workdir), span=plan)  # fmt: skip
        lab.up()
        self.lab = lab
        return lab.name

    def add_robot(self, name: str, index: int, pos: list[float]) -> str:
        robot = self._lab().add_robot(name, index=index, pos=(pos[0], pos[1]))
        return str(robot.mac)

    def add_remote(self, name: str, mac: str, pos: list[float]) -> None:
        self._lab().add_remote(name, mac=mac, pos=(pos[0], pos[1]))

    def start_all(self, robots: list[str], timeout: float, options: dict[str, Any]) -> None:
        self._lab().start_all(robots, timeout=timeout, **options)

    def stop(self, robot: str) -> int:
        return int(self._lab().stop(robot))

    def move(self, robot: str, pos: list[float]) -> None:
        self._lab().move(robot, (pos[0], pos[1]))

    def partition(self, groups: list[list[str]]) -> None:
        self._lab().partition(groups)

    def merge(self) -> None:
        self._lab().merge()

    def neighbors(self, robot: str) -> list[str]:
        return sorted(str(n["robot_id"]) for n in self._lab().client(robot).neighbors())

    def down(self) -> None:
        if self.lab is not None:
            lab, self.lab = self.lab, None
            lab.down()

    def handle(self, request: dict[str, Any]) -> dict[str, Any]:
        request = dict(request)
        op = request.pop("op", None)
        method: Callable[..., Any] | None = getattr(self, str(op), None) if op in OPS else None
        if method is None:
            return {"ok": False, "error": f"no operation {op!r} (one of {', '.join(OPS)})"}
        try:
            return {"ok": True, "result": method(**request)}
        except NetlabError as exc:
            return {"ok": False, "error": str(exc)}
        except (TypeError, ValueError, KeyError) as exc:
            return {"ok": False, "error": f"{op}: bad request: {type(exc).__name__}: {exc}"}


OPS = ("up", "add_robot", "add_remote", "start_all", "stop", "move", "partition", "merge",
       "neighbors", "down")  # fmt: skip


def serve(inp: TextIO, out: TextIO) -> None:
    """Answer requests until ``down`` or the end of `inp`; the lab goes down either way."""
    agent = Agent()
    try:
        for line in inp:
            if not line.strip():
                continue
            request: Any = None
            try:
                request = json.loads(line)
                if not isinstance(request, dict):
                    raise ValueError("a request is a JSON object")
            except ValueError as exc:
                answer: dict[str, Any] = {"ok": False, "error": f"not a request: {exc}"}
            else:
                answer = agent.handle(request)
            out.write(json.dumps(answer) + "\n")
            out.flush()
            if isinstance(request, dict) and request.get("op") == "down":
                break
    finally:
        agent.down()


_PID = os.getpid()


def _stop(signum: int, _frame: object) -> None:
    if os.getpid() != _PID:
        # A process forked from this one (pyroute2 makes namespaces and their sockets in
        # forked helpers, and stops them with SIGTERM): it dies as it would have without
        # this handler.  Raising there instead broke namespace creation now and then.
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)
        return
    raise SystemExit(128 + signum)


def main() -> int:
    global _PID
    _PID = os.getpid()
    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGHUP, _stop)  # the ssh session ended
    serve(sys.stdin, sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
