"""A host's share of a lab across hosts, run over ssh: ``python -m netlab.agent``.

The controller (`netlab.spanlab`) starts one agent per host over its ssh session and talks
to it in JSON lines on the session's stdin and stdout: one request per line,
``{"op": NAME, ...arguments}``, one answer per line, ``{"ok": true, "result": ...}`` or
``{"ok": false, "error": "what went wrong"}`` (a `NetlabError`'s sentence; anything else
is named with its type).  The agent holds one `Lab` with a `Span` (its robots, the other
hosts' robots as remote ones) and takes it down when told ``down``, when its stdin closes
(the controller or the connection died) or on SIGTERM/SIGHUP.

Operations: ``hello`` (its netlab version, the address its ssh session came in on, its
clock), ``up`` (name, seed, fleet, workdir, span: vni, local, hosts, port; range: the
range model as `netlab.ranges.model_to_json` writes it, or radius: a unit disc's; runtime,
image and addressing: the robots' kind and addresses, as `netlab.lab.Lab` takes them),
``add_robots`` (robots: each name, index, pos, mac, runtime; the medium loaded once: each one's
``robot`` answer) and ``add_remotes`` (remotes: each name, mac, pos),
``robot`` (robot: its ns, mac, iface and log here), the daemons' ``start_all`` (robots,
timeout, options), ``start``, ``restart`` (robot, timeout, options), ``stop`` (robot,
timeout), ``kill`` (robot) and ``daemons_ended``, the medium's ``move`` (robot, pos),
``partition`` (groups), ``merge``, ``set_pair_quality`` (a, b, loss, both), ``shape``
(robot, params) and ``batch`` (ops: medium operations applied as one change), what it
holds: ``links`` (the linked pairs whose receiver is here: each pair is judged on the
receiving host), ``positions``,
``read_log`` (robot: the tail of its daemon's log), tcpdumps: ``captures_start`` (targets:
"medium", whose frames are kept only from this host's robots so that each frame is captured
once across the hosts, or a robot: where each pcap is written) and ``captures_stop`` (their
counters), ``read_file`` (path, offset, size: a pcap's bytes, base64), ``usage`` (robots:
each running daemon's CPU and memory, as `netlab.procstat.Usage`, and the span's counters),
``span_bytes`` (what its end of the VXLAN carried), a robot's daemon's API: ``api`` (robot,
call, args; a refusal answers ``"api": {status, message, field}``) and ``neighbors`` (robot:
the robot ids its sdfrd lists), and ``down`` (keep_workdir: the folder it kept).
"""

from __future__ import annotations

import base64
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

from netlab.errors import NetlabError
from netlab.ranges import UnitDisc
from sdfr.errors import ApiError

#: What ``api`` may call of a robot's `sdfr.client.Client` (what the scenario engine asks).
API_CALLS = ("neighbors", "history", "publish", "unpublish", "self_info")
#: The operations ``batch`` applies as one change of the medium.
MEDIUM_OPS = ("move", "partition", "merge", "set_pair_quality", "shape")
#: ``read_log`` sends at most the last this many bytes of a log.
LOG_TAIL = 8 << 20
#: ``read_file`` sends at most this many bytes an answer.
FILE_CHUNK = 4 << 20


class Agent:
    """The operations on this host's share of the lab (see the module doc)."""

    def __init__(self) -> None:
        from netlab.capture import Capture
        from netlab.lab import Lab

        self.lab: Lab | None = None
        self.captures: list[Capture] = []

    def _lab(self) -> Any:
        if self.lab is None:
            raise NetlabError("no lab here yet: `up` first")
        return self.lab

    def hello(self) -> dict[str, Any]:
        from sdfr import __version__

        # "client-address client-port server-address server-port": the controller reached
        # this host at server-address, which the other hosts can reach it at as well.
        conn = os.environ.get("SSH_CONNECTION", "").split()
        return {
            "version": __version__,
            "address": conn[2] if len(conn) == 4 else None,
            "time": time.time(),
        }

    def up(self, name: str, seed: int, fleet: int, workdir: str | None, span: dict[str, Any],
           radius: float | None = None, range: dict[str, Any] | None = None,
           runtime: str = "namespace", image: str | None = None,
           addressing: str = "manual") -> str:  # fmt: skip
        from netlab.lab import Lab
        from netlab.ranges import RangeModel, model_from_json
        from netlab.vxlan import span_of

        if self.lab is not None:
            raise NetlabError(f"a lab {self.lab.name} is up here already")
        hosts = [str(h) for h in span["hosts"]]
        extra = {"port": int(span["port"])} if "port" in span else {}
        plan = span_of(str(span["lab"]), str(span["local"]), hosts, vni=int(span["vni"]), **extra)
        model: RangeModel = (
            model_from_json(range) if range is not None else UnitDisc(radius or 50.0)
        )
        kind: dict[str, Any] = {"runtime": runtime, **({"image": image} if image else {})}
        lab = Lab(name, seed=seed, fleet=fleet, range_model=model,
                  workdir=Path(workdir) if workdir is not None else None,
                  span=plan, addressing=addressing, **kind)  # fmt: skip
        lab.up()
        self.lab = lab
        return lab.name

    def robot(self, robot: str) -> dict[str, str]:
        r = self._lab().robot(robot)
        return {"ns": r.ns, "mac": r.mac, "iface": r.iface, "log": str(r.log)}

    def add_robots(self, robots: list[dict[str, Any]]) -> list[dict[str, str]]:
        """Robots here (each: name, index, pos, mac, runtime), the medium loaded once; each
        one's `robot` answer."""
        lab = self._lab()
        with lab.batch():
            for r in robots:
                lab.add_robot(r["name"], index=r["index"], pos=(r["pos"][0], r["pos"][1]),
                              mac=r.get("mac"), runtime=r.get("runtime"))  # fmt: skip
        return [self.robot(r["name"]) for r in robots]

    def add_remotes(self, remotes: list[dict[str, Any]]) -> None:
        """Other hosts' robots (each: name, mac, pos), the medium loaded once."""
        lab = self._lab()
        with lab.batch():
            for r in remotes:
                lab.add_remote(r["name"], mac=r["mac"], pos=(r["pos"][0], r["pos"][1]))

    def start_all(self, robots: list[str], timeout: float, options: dict[str, Any]) -> None:
        self._lab().start_all(robots, timeout=timeout, **options)

    def start(self, robot: str, timeout: float, options: dict[str, Any]) -> None:
        self._lab().start(robot, timeout=timeout, **options)

    def restart(self, robot: str, timeout: float, options: dict[str, Any]) -> None:
        self._lab().restart(robot, timeout=timeout, **options)

    def stop(self, robot: str, timeout: float | None = None) -> int:
        """(No timeout: the lab's own; `netlab.daemons` is not imported before a lab is up.)"""
        lab = self._lab()
        return int(lab.stop(robot) if timeout is None else lab.stop(robot, timeout))

    def kill(self, robot: str) -> None:
        self._lab().kill(robot)

    def daemons_ended(self) -> dict[str, str]:
        return dict(self._lab().daemons_ended())

    def move(self, robot: str, pos: list[float]) -> None:
        self._lab().move(robot, (pos[0], pos[1]))

    def partition(self, groups: list[list[str]]) -> None:
        self._lab().partition(groups)

    def merge(self) -> None:
        self._lab().merge()

    def set_pair_quality(self, a: str, b: str, loss: float | None, both: bool = True) -> None:
        self._lab().set_pair_quality(a, b, loss=loss, both=both)

    def shape(self, robot: str, params: dict[str, Any]) -> str:
        return str(self._lab().shape(robot, **params))

    def batch(self, ops: list[dict[str, Any]]) -> None:
        bad = [op.get("op") for op in ops if op.get("op") not in MEDIUM_OPS]
        if bad:
            raise NetlabError(f"batch: {bad} are not medium operations ({', '.join(MEDIUM_OPS)})")
        with self._lab().batch():
            for op in ops:
                kw = {k: v for k, v in op.items() if k != "op"}
                getattr(self, str(op["op"]))(**kw)

    def links(self) -> list[list[Any]]:
        lab = self._lab()
        here = set(lab.robots)
        return [[a, b, loss] for (a, b), loss in lab.links().items() if b in here]

    def positions(self) -> dict[str, list[float]]:
        return {name: [x, y] for name, (x, y) in self._lab().positions().items()}

    def read_log(self, robot: str) -> str | None:
        log: Path = self._lab().robot(robot).log
        try:
            with log.open("rb") as f:
                size = f.seek(0, os.SEEK_END)
                f.seek(max(0, size - LOG_TAIL))
                return f.read().decode(errors="replace")
        except FileNotFoundError:
            return None

    def captures_start(self, targets: list[str]) -> dict[str, str]:
        from netlab import naming
        from netlab.capture import DEFAULT_BPF, Capture, start_all

        lab = self._lab()
        folder = Path(lab.workdir) / "captures"
        folder.mkdir(parents=True, exist_ok=True)
        caps = []
        for target in targets:
            path = folder / f"{target}.pcap"
            if target == "medium":
                mine = " or ".join(f"ether src {r.mac}" for r in lab.robots.values())
                bpf = f"({DEFAULT_BPF}) and ({mine})" if mine else DEFAULT_BPF
                caps.append(Capture(lab.medium.ns, naming.BRIDGE, path, label="medium", bpf=bpf))
            else:
                r = lab.robot(target)
                caps.append(Capture(r.ns, r.iface, path, label=target))
        start_all(caps)
        self.captures += caps
        return {c.label: str(c.path) for c in caps}

    def captures_stop(self) -> dict[str, dict[str, int | None]]:
        from netlab.capture import stop_all

        caps, self.captures = self.captures, []
        stats = stop_all(caps)
        return {
            c.label: {"captured": s.captured, "received": s.received, "dropped": s.dropped}
            for c, s in zip(caps, stats, strict=False)
        }

    def usage(self, robots: list[str]) -> dict[str, Any]:
        from netlab import procstat

        lab = self._lab()
        kids = procstat.children()
        out: dict[str, list[float]] = {}
        for name in robots:
            pid = lab.daemon_pid(name) if name in lab.robots else None
            if pid is not None:
                u = procstat.Usage.read(procstat.tree(pid, kids))
                out[name] = [u.time, u.cpu_s, u.rss_kb, u.pss_kb, u.processes]
        return {"robots": out, "span": self.span_bytes()}

    def span_bytes(self) -> dict[str, int]:
        """What this host's end of the VXLAN has carried (the underlay's share of the lab)."""
        from netlab.vxlan import PORT_NAME

        lab = self._lab()
        got = subprocess.run(["ip", "-n", lab.medium.ns, "-j", "-s", "link", "show", PORT_NAME],
                             capture_output=True, text=True, timeout=10, check=False)  # fmt: skip
        if got.returncode != 0:
            raise NetlabError(f"span_bytes: {got.stderr.strip() or 'ip failed'}")
        stats = json.loads(got.stdout)[0]["stats64"]
        return {
            "tx_bytes": int(stats["tx"]["bytes"]),
            "tx_packets": int(stats["tx"]["packets"]),
            "rx_bytes": int(stats["rx"]["bytes"]),
            "rx_packets": int(stats["rx"]["packets"]),
        }

    def read_file(self, path: str, offset: int, size: int) -> str:
        lab = self._lab()
        target = Path(path).resolve()
        if not target.is_relative_to(Path(lab.workdir).resolve()):
            raise NetlabError(f"read_file: {path} is not in this host's share of the lab")
        with target.open("rb") as f:
            f.seek(offset)
            return base64.b64encode(f.read(min(size, FILE_CHUNK))).decode()

    def api(self, robot: str, call: str, args: dict[str, Any]) -> Any:
        if call not in API_CALLS:
            raise NetlabError(f"api: no call {call!r} (one of {', '.join(API_CALLS)})")
        return getattr(self._lab().client(robot), call)(**args)

    def neighbors(self, robot: str) -> list[str]:
        return sorted(str(n["robot_id"]) for n in self._lab().client(robot).neighbors())

    def down(self, keep_workdir: bool = False) -> str | None:
        """The share down; the folder kept (`keep_workdir`: daemon logs and state), if any."""
        caps, self.captures = self.captures, []
        for cap in caps:
            cap.kill()
        if self.lab is not None:
            lab, self.lab = self.lab, None
            kept = lab.down(keep_workdir=keep_workdir).kept
            return str(kept) if kept else None
        return None

    def handle(self, request: dict[str, Any]) -> dict[str, Any]:
        request = dict(request)
        op = request.pop("op", None)
        method: Callable[..., Any] | None = getattr(self, str(op), None) if op in OPS else None
        if method is None:
            return {"ok": False, "error": f"no operation {op!r} (one of {', '.join(OPS)})"}
        try:
            return {"ok": True, "result": method(**request)}
        except ApiError as exc:
            api = {"status": exc.status, "message": exc.message, "field": exc.field}
            return {"ok": False, "error": str(exc), "api": api}
        except NetlabError as exc:
            return {"ok": False, "error": str(exc)}
        except (TypeError, ValueError, KeyError) as exc:
            return {"ok": False, "error": f"{op}: bad request: {type(exc).__name__}: {exc}"}


OPS = ("hello", "up", "add_robots", "add_remotes", "robot",
       "start_all", "start", "restart", "stop", "kill", "daemons_ended", *MEDIUM_OPS, "batch",
       "links", "positions", "read_log", "captures_start", "captures_stop", "read_file", "usage",
       "span_bytes", "api", "neighbors", "down")  # fmt: skip


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
