"""The `netlab` command: bring labs up and down, look at them, run commands in robots.

    netlab up NAME --robots N [--seed S] [--radius R] [--spacing D] [--start]
    netlab down NAME
    netlab status [NAME]
    netlab exec NAME ROBOT -- CMD...
    netlab doctor

`up` leaves the lab running after the command exits; `down` removes it,
also when the program that made it died. Exit status 0 on success, 1 when
netlab could not do it (the message says why), 2 for a bad command line.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from netlab import cleanup, kernel, manifest, naming
from netlab.doctor import format_report, probe
from netlab.errors import LabNotFoundError, NetlabError, UnknownRobotError
from netlab.lab import Lab
from netlab.manifest import Manifest
from netlab.ranges import UnitDisc


def _lab_name(text: str) -> str:
    try:
        return naming.check_lab_name(text)
    except NetlabError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _metres(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected metres, got {text!r}") from None
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"must be >= 0 metres, got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="netlab",
        description="A fleet of SDfR robots on this machine: one network namespace per robot, "
        "running the real sdfrd, on a shared medium. Needs root.",
    )
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    up = sub.add_parser("up", help="create a lab and leave it running")
    up.add_argument("name", type=_lab_name, metavar="NAME", help="lab name: 1-8 of a-z 0-9")
    up.add_argument("--robots", type=_positive_int, required=True, metavar="N")
    up.add_argument("--seed", type=int, default=0, help="seed of the robots' MACs (default 0)")
    up.add_argument(
        "--radius", type=_metres, default=50.0, help="radio range in metres (default 50)"
    )
    up.add_argument(
        "--spacing",
        type=_metres,
        default=0.0,
        help="robots stand on a line this many metres apart (default 0: all in one spot)",
    )
    up.add_argument("--fleet", type=int, default=1, help="fleet id 0-255 (default 1)")
    up.add_argument("--workdir", help="where daemons keep state and logs (default: a new /tmp dir)")
    up.add_argument("--start", action="store_true", help="start sdfrd on every robot")
    up.add_argument(
        "--beacon-interval",
        type=float,
        default=None,
        metavar="S",
        help="sdfrd's beacon interval with --start (default: sdfrd's)",
    )

    down = sub.add_parser("down", help="stop and remove a lab (also one whose runner died)")
    down.add_argument("name", type=_lab_name, metavar="NAME")

    status = sub.add_parser("status", help="labs, their robots, namespaces and daemons")
    status.add_argument("name", type=_lab_name, nargs="?", metavar="NAME")
    status.add_argument("--json", action="store_true", help="machine-readable output")

    ex = sub.add_parser("exec", help="run a command inside a robot's namespace")
    ex.add_argument("name", type=_lab_name, metavar="NAME")
    ex.add_argument("robot", metavar="ROBOT")
    ex.add_argument("cmd", nargs=argparse.REMAINDER, metavar="-- CMD...")

    sub.add_parser("doctor", help="what this kernel supports, and what follows")
    return p


def cmd_up(args: argparse.Namespace) -> int:
    lab = Lab(
        args.name,
        seed=args.seed,
        fleet=args.fleet,
        workdir=Path(args.workdir) if args.workdir else None,
        range_model=UnitDisc(args.radius),
    )
    t0 = time.monotonic()
    lab.up()
    try:
        names = [f"r{i + 1}" for i in range(args.robots)]
        lab.add_robots(names, {n: (i * args.spacing, 0.0) for i, n in enumerate(names)})
        print(f"lab {args.name}: {args.robots} robots up in {time.monotonic() - t0:.2f} s")
        if args.start:
            t1 = time.monotonic()
            opts: dict[str, Any] = {}
            if args.beacon_interval is not None:
                opts["beacon_interval"] = args.beacon_interval
            lab.start_all(timeout=max(60.0, 2.0 * args.robots), **opts)
            print(f"sdfrd healthy on {args.robots} robots in {time.monotonic() - t1:.2f} s")
    except BaseException:
        lab.down()
        raise
    print(f"workdir {lab.workdir}")
    print(f"`netlab status {args.name}` shows it; `netlab down {args.name}` removes it")
    lab.detach()
    return 0


def cmd_down(args: argparse.Namespace) -> int:
    result = cleanup.sweep(args.name, manifest.load(args.name))
    if result.empty:
        print(f"no lab {args.name}: nothing to remove")
        return 0
    parts = [f"{len(result.namespaces)} namespaces"]
    if result.processes:
        parts.append(f"{len(result.processes)} processes")
    if result.workdir:
        parts.append(f"workdir {result.workdir}")
    print(f"lab {args.name} removed: " + ", ".join(parts))
    return 0


def _proc_alive(rec: manifest.ProcRecord) -> bool:
    return cleanup.running(rec.pid) and cleanup.start_time(rec.pid) == rec.start


def lab_status(record: Manifest) -> dict[str, Any]:
    """What is left of a lab, from its manifest and the kernel."""
    present = set(kernel.list_ns(naming.prefix(record.name)))
    daemons: dict[str, int] = {}
    for rec in record.processes:
        if rec.role == "sdfrd" and _proc_alive(rec):
            daemons[rec.robot] = rec.pid
    runner_alive = (
        cleanup.running(record.runner_pid)
        and cleanup.start_time(record.runner_pid) == record.runner_start
    )
    return {
        "name": record.name,
        "runner": {"pid": record.runner_pid, "alive": runner_alive},
        "workdir": record.workdir,
        "medium": naming.air_ns(record.name) in present,
        "robots": {
            name: {
                "namespace": r.ns,
                "present": r.ns in present,
                "address": r.address,
                "mac": r.mac,
                "sdfrd": daemons.get(name),
            }
            for name, r in record.robots.items()
        },
        "processes": sum(1 for p in record.processes if _proc_alive(p)),
    }


def orphans() -> dict[str, list[str]]:
    """Namespaces named like a lab's whose lab has no manifest: lab name -> namespaces."""
    known = set(manifest.names())
    out: dict[str, list[str]] = {}
    for ns in kernel.list_ns(naming.NS_PREFIX):
        lab = ns[len(naming.NS_PREFIX) :].split("-", 1)[0]
        if naming.LAB_NAME_RE.match(lab) and lab not in known and "-" in ns[3:]:
            out.setdefault(lab, []).append(ns)
    return out


def cmd_status(args: argparse.Namespace) -> int:
    names = [args.name] if args.name else manifest.names()
    labs = []
    for name in names:
        record = manifest.load(name)
        if record is None:
            if args.name:
                left = kernel.list_ns(naming.prefix(name))
                hint = f" (but namespaces {', '.join(left)}: `netlab down {name}`)" if left else ""
                raise LabNotFoundError(f"no lab {name} is up{hint}")
            continue
        labs.append(lab_status(record))
    stray = {k: v for k, v in orphans().items() if not args.name or k == args.name}
    if args.json:
        print(json.dumps({"labs": labs, "orphans": stray}, indent=1))
        return 0
    if not labs and not stray:
        print("no labs")
    for lab in labs:
        runner = lab["runner"]
        who = f"runner pid {runner['pid']} {'alive' if runner['alive'] else 'gone'}"
        print(f"lab {lab['name']}: {len(lab['robots'])} robots, {who}, workdir {lab['workdir']}")
        if not lab["medium"]:
            print("  medium namespace MISSING")
        for name, r in lab["robots"].items():
            ns = "ok" if r["present"] else "MISSING"
            daemon = f"sdfrd pid {r['sdfrd']}" if r["sdfrd"] else "no sdfrd"
            print(f"  {name:<12} {r['address']:<16} {r['mac']}  namespace {ns}  {daemon}")
    for lab_name, nss in sorted(stray.items()):
        print(f"left behind (no manifest): {', '.join(nss)}; `netlab down {lab_name}` removes them")
    return 0


def cmd_exec(args: argparse.Namespace) -> int:
    cmd = list(args.cmd)
    if cmd and cmd[0] == "--":
        cmd = cmd[1:]
    if not cmd:
        raise NetlabError("exec: no command given (netlab exec NAME ROBOT -- CMD...)")
    record = manifest.load(args.name)
    if record is None:
        raise LabNotFoundError(f"no lab {args.name} is up (`netlab status` lists labs)")
    robot = record.robots.get(args.robot)
    if robot is None:
        raise UnknownRobotError(
            f"lab {args.name} has no robot {args.robot!r} (robots: {', '.join(record.robots)})"
        )
    if robot.ns not in kernel.list_ns():
        raise NetlabError(f"the namespace {robot.ns} of robot {args.robot} is gone")
    argv = kernel.ns_argv(robot.ns, cmd)
    sys.stdout.flush()
    os.execvp(argv[0], argv)


def cmd_doctor(args: argparse.Namespace) -> int:
    caps = probe()
    print(format_report(caps))
    return 0 if caps.lab else 1


COMMANDS = {
    "up": cmd_up,
    "down": cmd_down,
    "status": cmd_status,
    "exec": cmd_exec,
    "doctor": cmd_doctor,
}


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return COMMANDS[args.command](args)
    except NetlabError as exc:
        print(f"netlab: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("netlab: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
