"""A lab across hosts left up: `netlab up NAME --hosts H1,H2,...` (or a topology with a
``[hosts]`` table).

A lab across hosts is held by its ssh sessions: each host's agent takes its share down when
its session ends (`netlab.agent`).  So `up` leaves a *keeper* behind, a process of its own
session (``python -m netlab.spankeep``) that holds the `SpanLab` and its sessions and answers
the other commands on a Unix socket: ``status``, ``partition``, ``merge``, ``shape`` and
``down``.  Its record, ``<run dir>/span/<lab>.json`` (pid, hosts, each host's share's name,
where each robot is), says where it is; its log is ``<lab>.log`` beside it.

Clean-up: `down` asks the keeper to take every host's share down and end.  A keeper that is
gone (killed, the machine's session ended) took the sessions with it, so every host still
reached took its share down by itself; `down` then also runs `netlab down SHARE` on each host
over ssh, for a host that was cut off at that moment, and names the hosts it cannot reach.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from netlab import manifest, naming
from netlab.errors import LabExistsError, LabNotFoundError, NetlabError
from netlab.hosts import HostError, Ssh
from netlab.ranges import linked_pairs

#: How long a command waits for the keeper's answer (s): `down` takes every share down.
ANSWER_TIMEOUT = 300.0
#: The operations the keeper answers.
OPS = ("status", "partition", "merge", "shape", "down")


def span_dir() -> Path:
    return manifest.run_dir() / "span"


def record_path(name: str) -> Path:
    return span_dir() / f"{name}.json"


def socket_path(name: str) -> Path:
    return span_dir() / f"{name}.sock"


def log_path(name: str) -> Path:
    return span_dir() / f"{name}.log"


@dataclass(slots=True)
class SpanRecord:
    """Where a lab across hosts is held, and what it holds."""

    name: str
    pid: int  # the keeper
    hosts: list[str]  # ssh destinations, in order
    shares: dict[str, str]  # host -> its share's lab name there
    robots: dict[str, str]  # robot -> host
    ssh_config: str | None
    python: str
    started: float

    def ssh(self, host: str) -> Ssh:
        config = Path(self.ssh_config) if self.ssh_config else None
        return Ssh(host, config, self.python)

    def keeper_alive(self) -> bool:
        try:
            os.kill(self.pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:
            return True
        cmd = Path(f"/proc/{self.pid}/cmdline")
        with contextlib.suppress(OSError):
            return b"netlab.spankeep" in cmd.read_bytes()
        return False


def load(name: str) -> SpanRecord | None:
    try:
        data = json.loads(record_path(name).read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        raise NetlabError(
            f"lab {name}: its record {record_path(name)} is unreadable: {exc}"
        ) from None
    try:
        return SpanRecord(**data)
    except TypeError as exc:
        raise NetlabError(f"lab {name}: its record {record_path(name)} is damaged: {exc}") from None


def names() -> list[str]:
    with contextlib.suppress(OSError):
        return sorted(p.stem for p in span_dir().glob("*.json"))
    return []


# -- the commands' side -------------------------------------------------------------------------


def up(args: argparse.Namespace, hosts: list[str]) -> int:
    """Start the keeper for `args` (`netlab up`'s) across `hosts`; relay what it says while
    it brings the lab up; 0 once it holds the lab."""
    naming.check_lab_name(args.name)
    if manifest.load(args.name) is not None or load(args.name) is not None:
        raise LabExistsError(f"lab {args.name} is up already (`netlab down {args.name}` first)")
    span_dir().mkdir(parents=True, exist_ok=True)
    plan = {
        key: getattr(args, key, None)
        for key in ("name", "robots", "seed", "fleet", "radius", "spacing", "runtime", "medium",
                    "image", "start", "beacon_interval", "workdir", "host_python")
    }  # fmt: skip
    plan["topology"] = args.topology
    plan["cwd"] = os.getcwd()
    plan["hosts"] = hosts
    plan["ssh_config"] = str(Path(args.ssh_config).resolve()) if args.ssh_config else None
    with open(log_path(args.name), "ab") as log:
        keeper = subprocess.Popen(
            [sys.executable, "-m", "netlab.spankeep"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=log,
            start_new_session=True,
            text=True,
        )
    assert keeper.stdin is not None and keeper.stdout is not None
    keeper.stdin.write(json.dumps(plan) + "\n")
    keeper.stdin.close()
    for line in keeper.stdout:  # (until it holds the lab or gives up; Ctrl-C: it sees us go)
        if line.startswith("{"):
            said = json.loads(line)
            if said.get("ready"):
                return 0
            keeper.wait(30)
            written = log_path(args.name)
            if written.exists() and not written.stat().st_size:  # (the error says it all)
                written.unlink()
            raise NetlabError(str(said.get("error")))
        print(line, end="", flush=True)
    code = keeper.wait(30)
    tail = _tail(log_path(args.name))
    raise NetlabError(
        f"lab {args.name}: its keeper ended before the lab was up (exit {code}){tail}; "
        f"its log: {log_path(args.name)}"
    )


def _tail(log: Path) -> str:
    with contextlib.suppress(OSError):
        lines = log.read_text(errors="replace").strip().splitlines()
        if lines:
            return ": " + lines[-1]
    return ""


def call(name: str, op: str, **kw: Any) -> dict[str, Any]:
    """Ask lab `name`'s keeper; its answer, or NetlabError saying why not."""
    record = load(name)
    if record is None:
        raise LabNotFoundError(f"no lab {name} is up across hosts")
    if not record.keeper_alive():
        raise NetlabError(
            f"lab {name}: its keeper (pid {record.pid}) is gone, and the hosts took their "
            f"shares down with it: `netlab down {name}` checks each host and removes the record"
        )
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(ANSWER_TIMEOUT)
        try:
            sock.connect(str(socket_path(name)))
            sock.sendall((json.dumps({"op": op, **kw}) + "\n").encode())
            data = b""
            while not data.endswith(b"\n"):
                chunk = sock.recv(65536)
                if not chunk:
                    break
                data += chunk
        except OSError as exc:
            raise NetlabError(
                f"lab {name}: its keeper (pid {record.pid}) did not answer: {exc}"
            ) from None
    if not data:
        raise NetlabError(f"lab {name}: its keeper (pid {record.pid}) closed without answering")
    answer: dict[str, Any] = json.loads(data)
    if not answer.get("ok"):
        raise NetlabError(f"lab {name}: {answer.get('error')}")
    return answer


def down(name: str, record: SpanRecord, keep_workdir: bool = True) -> list[str]:
    """Take lab `name` down on every host, keeping each share's folder there unless not
    `keep_workdir`; what was done, a line each (HostError naming the hosts that could not
    be reached, after the others are clean)."""
    if record.keeper_alive():
        lines: list[str] = call(name, "down", keep_workdir=keep_workdir)["lines"]
        _wait_gone(record.pid)
        log_path(name).unlink(missing_ok=True)
        return lines
    lines = [f"its keeper (pid {record.pid}) was gone: asking each host"]
    failed = []
    for host in record.hosts:
        share = record.shares[host]
        ssh = record.ssh(host)
        try:
            argv = [record.python, "-m", "netlab.cli", "down", share]
            argv += [] if keep_workdir else ["--cleanup"]
            said = ssh.run(argv, f"netlab down {share}")
            lines.append(f"host {host}: {(said.strip().splitlines() or ['done'])[0]}")
        except HostError as exc:
            failed.append(str(exc))
        finally:
            ssh.close()
    _forget(name)
    if failed:
        raise HostError(f"lab {name}: record removed; not cleaned up: " + "; ".join(failed))
    log_path(name).unlink(missing_ok=True)
    return lines


def _wait_gone(pid: int, within: float = 30.0) -> None:
    end = time.monotonic() + within
    while time.monotonic() < end:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return
        time.sleep(0.05)


def _forget(name: str) -> None:
    for path in (record_path(name), socket_path(name)):
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


def elsewhere(name: str, robot: str | None, what: str) -> NetlabError:
    """The error for a command that runs on one machine (exec, logs, capture, pingall) given
    a lab across hosts: where to run it instead."""
    record = load(name)
    assert record is not None
    if robot is not None and robot in record.robots:
        host = record.robots[robot]
        share = record.shares[host]
        return NetlabError(
            f"lab {name} runs across hosts: {robot} is on {host}, in its share {share} there: "
            f"`ssh {host} netlab {what} {share} {robot} ...`"
        )
    shares = ", ".join(f"{h}: {s}" for h, s in record.shares.items())
    return NetlabError(
        f"lab {name} runs across hosts: `netlab {what}` works on one host's share at a time, "
        f"there ({shares})"
    )


# -- the keeper ---------------------------------------------------------------------------------


class Keeper:
    """Holds one `SpanLab` and answers on its socket until `down` or a signal."""

    def __init__(self, plan: dict[str, Any]) -> None:
        from netlab.scenario.topology import for_up

        self.plan = plan
        self.name = str(plan["name"])
        args = argparse.Namespace(**{**plan, "hosts": None})
        if plan["topology"] and not os.path.isabs(plan["topology"]):
            args.topology = str(Path(plan["cwd"]) / plan["topology"])
            if not Path(args.topology).exists():
                args.topology = plan["topology"]  # a bundled scenario's name
        self.sc = for_up(args)
        self.stopping = False

    def bring_up(self) -> Any:
        from netlab import scenario
        from netlab.ranges import UnitDisc
        from netlab.scenario.topology import start_for_up
        from netlab.spanlab import SpanLab, check_medium

        sc, plan = self.sc, self.plan
        config = Path(plan["ssh_config"]) if plan["ssh_config"] else None
        python = plan["host_python"] or "python3"
        hosts: list[tuple[Ssh, str | None]] = [
            (Ssh(h, config, python), None) for h in plan["hosts"]
        ]
        placed = {r: h for r, h in sc.placement().items() if h in plan["hosts"]}
        lab = SpanLab(self.name, hosts, place=placed, seed=sc.seed, fleet=sc.fleet,
                      range_model=UnitDisc(sc.radius), workdir=plan["workdir"],
                      runtime=sc.runtime, image=plan["image"] if sc.runtime == "docker" else None,
                      addressing=sc.addressing)  # fmt: skip
        check_medium(self.name, sc.medium)
        t0 = time.monotonic()
        lab.up()
        try:
            scenario.add_robots(lab, sc)
            n = len(sc.names)
            say(f"lab {self.name}: {n} robots {lab.where} up in {time.monotonic() - t0:.2f} s")
            for host, share in lab.part_names().items():
                mine = [r for r, h in lab.placed.items() if h == host]
                say(f"  host {host}: share {share}: {', '.join(mine) or 'no robot'}")
            for line in scenario.lay_out(lab, sc):
                say(f"  {line}")
            if plan["start"]:
                say(start_for_up(lab, sc, plan["beacon_interval"], bool(plan["topology"])))
            else:
                say("sdfrd runs on no robot: `netlab up ... --start` starts it on every robot")
        except BaseException:
            lab.down()
            raise
        return lab

    def serve(self, lab: Any) -> None:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as server:
            path = socket_path(self.name)
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
            server.bind(str(path))
            os.chmod(path, 0o600)
            server.listen(8)
            server.settimeout(1.0)
            while not self.stopping:
                try:
                    conn, _ = server.accept()
                except TimeoutError:
                    continue
                except InterruptedError:
                    continue
                with conn:
                    conn.settimeout(10.0)
                    answer = self.answer(lab, _read_line(conn))
                    with contextlib.suppress(OSError):
                        conn.sendall((json.dumps(answer) + "\n").encode())

    def answer(self, lab: Any, line: bytes) -> dict[str, Any]:
        try:
            request = json.loads(line)
            op = request.pop("op", None)
            if op not in OPS:
                return {"ok": False, "error": f"unknown request {op!r}: one of {', '.join(OPS)}"}
            return {"ok": True, **getattr(self, f"op_{op}")(lab, **request)}
        except NetlabError as exc:
            return {"ok": False, "error": str(exc)}
        except (ValueError, TypeError) as exc:
            return {"ok": False, "error": f"a bad request: {exc}"}

    def op_status(self, lab: Any) -> dict[str, Any]:
        hosts = {}
        for host, part in lab.parts.items():
            code = part.proc.poll()
            hosts[host] = {
                "share": lab.part_names()[host],
                "robots": [r for r, h in lab.placed.items() if h == host],
                "session": "up" if code is None else f"ended (exit {code})",
            }
        try:
            pairs = linked_pairs(lab.links())
            ended = lab.daemons_ended()
        except HostError as exc:
            pairs, ended = None, {"?": str(exc)}
        return {"hosts": hosts, "linked_pairs": pairs, "robots": len(lab.placed),
                "daemons_ended": ended, "where": lab.where, "pid": os.getpid()}  # fmt: skip

    def op_partition(self, lab: Any, groups: list[list[str]]) -> dict[str, Any]:
        for group in groups:
            for robot in group:
                lab.host_of(robot)
        try:
            lab.partition(groups)
        except ValueError as exc:
            raise NetlabError(f"partition: {exc}") from None
        return {"linked_pairs": linked_pairs(lab.links())}

    def op_merge(self, lab: Any) -> dict[str, Any]:
        lab.merge()
        return {"linked_pairs": linked_pairs(lab.links())}

    def op_shape(self, lab: Any, robots: list[str], params: dict[str, Any]) -> dict[str, Any]:
        for robot in robots:
            lab.host_of(robot)
        return {"shaped": {r: lab.shape(r, **params) for r in robots}}

    def op_down(self, lab: Any, keep_workdir: bool = True) -> dict[str, Any]:
        self.stopping = True
        shares = lab.part_names()
        kept = lab.down(keep_workdir=keep_workdir)  # (HostError: names the hosts not reached)
        return {
            "lines": [
                f"host {h}: share {s} down" + (f", kept its folder {kept[h]}" if h in kept else "")
                for h, s in shares.items()
            ]
        }


def _read_line(conn: socket.socket) -> bytes:
    data = b""
    while not data.endswith(b"\n") and len(data) < 1 << 20:
        chunk = conn.recv(65536)
        if not chunk:
            break
        data += chunk
    return data


def say(line: str) -> None:
    print(line, flush=True)


def keeper_main() -> int:
    plan = json.loads(sys.stdin.readline())
    name = str(plan["name"])
    keeper = Keeper(plan)

    def stop(signum: int, frame: object) -> None:
        keeper.stopping = True

    for signum in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT):
        signal.signal(signum, stop)
    try:
        record_path(name).parent.mkdir(parents=True, exist_ok=True)
        with open(record_path(name), "x") as f:  # the name's claim
            f.write("{}")
    except FileExistsError:
        print(json.dumps({"error": f"lab {name} is up already"}), flush=True)
        return 1
    lab = None
    try:
        try:
            lab = keeper.bring_up()
        except NetlabError as exc:
            print(json.dumps({"error": str(exc)}), flush=True)
            return 1
        record = SpanRecord(
            name, os.getpid(), list(plan["hosts"]), lab.part_names(), dict(lab.placed),
            plan["ssh_config"], plan["host_python"] or "python3", time.time(),
        )  # fmt: skip
        tmp = record_path(name).with_suffix(".tmp")
        tmp.write_text(json.dumps(asdict(record)))
        tmp.replace(record_path(name))
        say(f"`netlab status {name}` shows the lab; `netlab down {name}` takes it off every host")
        print(json.dumps({"ready": True}), flush=True)
        with open(os.devnull, "w") as null:  # `up` has gone: nothing reads this any more
            os.dup2(null.fileno(), sys.stdout.fileno())
        keeper.serve(lab)
        return 0
    finally:
        if lab is not None and lab.parts:
            with contextlib.suppress(HostError):
                lab.down()
        _forget(name)


if __name__ == "__main__":
    raise SystemExit(keeper_main())
