"""The `netlab` actions on a lab left up: up, down, status, partition, merge, shape, exec,
logs, pingall.  The parser and the other actions are in `netlab.cli`."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from netlab import cleanup, docker, kernel, manifest, naming, pingall, spankeep
from netlab.errors import LabNotFoundError, NetlabError, UnknownRobotError
from netlab.lab import Lab
from netlab.manifest import Manifest, RobotRecord
from netlab.ranges import Topology, UnitDisc, linked_pairs
from netlab.status import format_status, lab_status, orphans
from sdfr.hints import did_you_mean

if TYPE_CHECKING:
    from netlab.scenario import Scenario


def _topology(args: argparse.Namespace) -> Scenario:
    """The lab `up` makes (`netlab.scenario.topology.for_up`)."""
    from netlab.scenario.topology import for_up

    return for_up(args)


def cmd_up(args: argparse.Namespace) -> int:
    from netlab import scenario
    from netlab.scenario.topology import start_for_up

    sc = _topology(args)
    hosts = host_list(getattr(args, "hosts", None)) or list(sc.hosts)
    if hosts:  # a lab across hosts: held by a keeper (netlab.spankeep)
        return spankeep.up(args, hosts)
    lab = Lab(
        args.name,
        seed=sc.seed,
        fleet=sc.fleet,
        workdir=Path(args.workdir) if args.workdir else None,
        range_model=UnitDisc(sc.radius),
        addressing=sc.addressing,
        runtime=sc.runtime,
        image=args.image,
        air=sc.medium,
    )
    t0 = time.monotonic()
    lab.up()
    try:
        scenario.add_robots(lab, sc)
        kinds = {r.runtime for r in lab.robots.values()}
        kind = (
            " (containers)"
            if kinds == {"docker"}
            else " (some containers)"
            if len(kinds) > 1
            else ""
        )
        n = len(sc.names)
        print(f"lab {args.name}: {n} robots{kind} up in {time.monotonic() - t0:.2f} s")
        for line in scenario.lay_out(lab, sc):
            print(f"  {line}")
        if args.start:
            print(start_for_up(lab, sc, args.beacon_interval, args.topology is not None))
        else:
            print(
                "sdfrd runs on no robot: `netlab up ... --start` starts it on every robot; "
                f"or start one by hand: `netlab exec {args.name} r1 -- sdfrd --iface eth0`"
            )
    except BaseException:
        lab.down()
        raise
    print(f"folder {lab.workdir} (daemon logs and state; kept by `netlab down`)")
    print(f"`netlab status {args.name}` shows the lab; `netlab down {args.name}` removes it")
    lab.detach()
    return 0


@contextlib.contextmanager
def _attached(name: str) -> Iterator[Lab]:
    """The running lab `name`, taken over for one change (`Lab.attach`), then left again."""
    with manifest.locked(name):
        lab = Lab.attach(name)
        try:
            yield lab
        finally:
            lab.detach()


def _links_summary(lab: Lab) -> str:
    return f"{linked_pairs(lab.links())} linked pairs of {len(lab.robots)} robots"


def host_list(text: str | None) -> list[str]:
    """`--hosts`' ssh destinations."""
    return [h.strip() for h in (text or "").split(",") if h.strip()]


def _across(name: str, op: str, **kw: Any) -> dict[str, Any] | None:
    """The keeper's answer when `name` is a lab across hosts (None: it is not)."""
    return spankeep.call(name, op, **kw) if spankeep.load(name) is not None else None


def cmd_partition(args: argparse.Namespace) -> int:
    if (span := _across(args.name, "partition", groups=args.groups)) is not None:
        print(f"lab {args.name}: partition {' | '.join(','.join(g) for g in args.groups)}; "
              f"{span['linked_pairs']} linked pairs across its hosts")  # fmt: skip
        return 0
    with _attached(args.name) as lab:
        try:
            lab.partition(args.groups)
        except ValueError as exc:  # (the same robot in two groups)
            raise NetlabError(f"partition: {exc}") from None
        rest = [r for r in lab.robots if not any(r in g for g in args.groups)]
        groups = [",".join(g) for g in args.groups] + ([",".join(rest)] if rest else [])
        print(f"lab {args.name}: partition {' | '.join(groups)}; {_links_summary(lab)}")
    return 0


def cmd_merge(args: argparse.Namespace) -> int:
    if (span := _across(args.name, "merge")) is not None:
        print(f"lab {args.name}: merged; {span['linked_pairs']} linked pairs across its hosts")
        return 0
    with _attached(args.name) as lab:
        lab.merge()
        print(f"lab {args.name}: merged; {_links_summary(lab)}")
    return 0


SHAPE_PARAMS = ("delay", "jitter", "loss", "duplicate", "reorder", "corrupt", "rate")


def cmd_shape(args: argparse.Namespace) -> int:
    params = {k: getattr(args, k) for k in SHAPE_PARAMS if getattr(args, k) is not None}
    if args.clear == bool(params):
        raise NetlabError("shape: give shaping parameters (--loss, --delay, ...) or --clear")
    if (span := _across(args.name, "shape", robots=args.robots, params=params)) is not None:
        for robot, what in span["shaped"].items():
            print(f"lab {args.name}: {robot}: {what}")
        return 0
    with _attached(args.name) as lab:
        for robot in args.robots:
            lab.robot(robot)  # all known before any is shaped
        for robot in args.robots:
            shape = lab.shape(robot, **params)
            what = ", ".join(f"{k} {v}" for k, v in dataclasses.asdict(shape).items() if v)
            print(f"lab {args.name}: {robot}: {what or 'no shaping'}")
    return 0


def cmd_down(args: argparse.Namespace) -> int:
    span = spankeep.load(args.name)
    if span is not None:
        lines = spankeep.down(args.name, span, keep_workdir=not args.cleanup)
        print(f"lab {args.name} removed from {len(span.hosts)} hosts")
        for line in lines:
            print(f"  {line}")
        return 0
    try:
        record = manifest.load(args.name)
    except NetlabError as exc:  # a damaged manifest: swept by the lab's name alone
        print(f"netlab: {exc}", file=sys.stderr)
        record = None
    result = cleanup.sweep(args.name, record, keep_workdir=not args.cleanup)
    if result.empty:
        print(f"no lab {args.name}: nothing to remove")
        return 0
    parts = [f"{len(result.namespaces)} namespaces"]
    if result.containers:
        parts.append(f"{len(result.containers)} containers")
    if result.radios:
        parts.append(f"{len(result.radios)} radios")
    if result.processes:
        parts.append(f"{len(result.processes)} processes")
    if result.workdir:
        parts.append(f"folder {result.workdir}")
    print(f"lab {args.name} removed: " + ", ".join(parts))
    if result.kept:
        again = "" if record is None or record.workdir_owned else " (given with --workdir)"
        print(
            f"kept its folder {result.kept}{again}: daemon logs (`netlab logs {result.kept} "
            f"ROBOT`) and state; `rm -r {result.kept}` removes it, as `netlab down --cleanup` "
            "would have"
        )
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    names = [args.name] if args.name else manifest.names()
    across: dict[str, dict[str, Any]] = {}
    for name in [args.name] if args.name else spankeep.names():
        try:
            if spankeep.load(name) is not None:
                across[name] = spankeep.call(name, "status")
        except NetlabError as exc:  # (a dead keeper: said, the others still listed)
            if args.name:
                raise
            across[name] = {"error": str(exc)}
    labs = []
    for name in names:
        record = manifest.load(name)
        if record is None:
            if name in across:
                continue
            if args.name:
                left = kernel.list_ns(naming.prefix(name))
                hint = f" (but namespaces {', '.join(left)}: `netlab down {name}`)" if left else ""
                up = did_you_mean(name, manifest.names()) if not left else ""
                raise LabNotFoundError(f"no lab {name} is up{hint}{up}")
            continue
        labs.append(lab_status(record))
    stray = {k: v for k, v in orphans().items() if not args.name or k == args.name}
    if args.json:
        print(json.dumps({"labs": labs, "across_hosts": across, "orphans": stray}, indent=1))
        return 0
    if labs or stray or not across:
        print(format_status(labs, stray))
    for name, span in across.items():
        if "error" in span:
            print(f"lab {name} (across hosts): {span['error']}")
            continue
        print(f"lab {name}: {span['robots']} robots {span['where']}, keeper pid {span['pid']}; "
              f"{span['linked_pairs']} linked pairs")  # fmt: skip
        for host, h in span["hosts"].items():
            print(f"  host {host}: share {h['share']} ({h['session']}): {', '.join(h['robots'])}")
        for robot, why in span["daemons_ended"].items():
            print(f"  {robot}: sdfrd ended: {why}")
    return 0


def lab_record(name: str, robot: str | None = None, what: str = "exec") -> Manifest:
    record = manifest.load(name)
    if record is None and spankeep.load(name) is not None:
        raise spankeep.elsewhere(name, robot, what)
    if record is None:
        hint = did_you_mean(name, manifest.names())
        raise LabNotFoundError(f"no lab {name} is up{hint} (`netlab status` lists labs)")
    return record


def robot_record(record: Manifest, name: str) -> RobotRecord:
    robot = record.robots.get(name)
    if robot is None:
        raise UnknownRobotError(
            f"lab {record.name} has no robot {name!r}{did_you_mean(name, record.robots)} "
            f"(robots: {', '.join(record.robots)})"
        )
    return robot


def split_exec(words: list[str], all_robots: bool) -> tuple[str | None, list[str]]:
    """(robot or None for --all, command) from exec's words after NAME: ``ROBOT -- CMD...``,
    or ``-- CMD...`` with --all (which may also stand among them)."""
    if words[:1] == ["--all"]:
        all_robots, words = True, words[1:]
    robot = None
    if not all_robots:
        if not words or words[0] == "--":
            raise NetlabError("exec: name a robot, or --all (netlab exec NAME ROBOT -- CMD...)")
        robot, words = words[0], words[1:]
    if words[:1] == ["--"]:
        words = words[1:]
    if not words:
        after = f" after the robot {robot!r}" if robot else ""
        raise NetlabError(
            f"exec: no command given{after} (netlab exec NAME ROBOT -- CMD..., or --all NAME -- "
            "CMD...)"
        )
    return robot, words


def _exec_argv(robot: RobotRecord, cmd: list[str], *, interactive: bool) -> list[str]:
    if robot.ns not in kernel.list_ns():
        raise NetlabError(f"the namespace {robot.ns} of the robot is gone: `netlab status`")
    if robot.runtime == "docker":
        return docker.exec_argv(robot.ns, cmd, stdin=interactive, tty=interactive)
    return kernel.ns_argv(robot.ns, cmd)


def cmd_exec(args: argparse.Namespace) -> int:
    robot_name, cmd = split_exec(list(args.cmd), args.all)
    record = lab_record(args.name, robot_name)
    if robot_name is not None:
        robot = robot_record(record, robot_name)
        argv = _exec_argv(robot, cmd, interactive=sys.stdin.isatty())
        sys.stdout.flush()
        os.execvp(argv[0], argv)
    return exec_all(record, cmd, sys.stdout)


def exit_status(code: int) -> int:
    """A shell's exit status of a process's return code (a signal: 128 + its number)."""
    return 128 - code if code < 0 else code


def exec_all(record: Manifest, cmd: list[str], out: TextIO) -> int:
    """Run `cmd` in every robot at once, each output line prefixed with the robot's name;
    the worst exit status."""
    argvs = {name: _exec_argv(r, cmd, interactive=False) for name, r in record.robots.items()}
    width = max(len(n) for n in argvs)
    lock = threading.Lock()
    procs: dict[str, subprocess.Popen[bytes]] = {}

    def copy(name: str, proc: subprocess.Popen[bytes]) -> None:
        assert proc.stdout is not None
        for raw in proc.stdout:
            line = raw.decode(errors="replace").rstrip("\n")
            with lock:
                print(f"{name:<{width}} | {line}", file=out, flush=True)

    threads = []
    try:
        for name, argv in argvs.items():
            proc = subprocess.Popen(
                argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT
            )
            procs[name] = proc
            thread = threading.Thread(target=copy, args=(name, proc), daemon=True)
            thread.start()
            threads.append(thread)
        codes = {name: proc.wait() for name, proc in procs.items()}
        for thread in threads:
            thread.join()
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    failed = {n: exit_status(c) for n, c in codes.items() if c}
    if failed:
        text = ", ".join(f"{n} {c}" for n, c in failed.items())
        print(f"netlab: exit status {text} of {len(codes)} robots", file=sys.stderr)
    return max((exit_status(c) for c in codes.values()), default=0)


def log_of(ref: str, robot: str) -> Path:
    """The daemon log of `robot` in lab `ref` (a lab up) or in folder `ref` (kept by down)."""
    folder = Path(ref)
    if os.sep in ref or ref.startswith("."):
        if not folder.is_dir():
            raise NetlabError(f"no folder {ref} (give a lab's name, or the folder down kept)")
    else:
        try:
            record = lab_record(naming.check_lab_name(ref), robot, "logs")
        except LabNotFoundError as exc:
            raise LabNotFoundError(f"{exc}; after `netlab down`, give the folder it kept") from None
        robot_record(record, robot)
        folder = Path(record.workdir)
    log = folder / robot / "sdfrd.log"
    if not log.exists():
        robots = sorted(p.parent.name for p in folder.glob("*/sdfrd.log"))
        hint = did_you_mean(robot, robots)
        raise NetlabError(
            f"no daemon log {log}{hint}: sdfrd never ran on {robot} "
            f"(logs in {folder}: {', '.join(robots) or 'none'})"
        )
    return log


def cmd_logs(args: argparse.Namespace) -> int:
    log = log_of(args.lab, args.robot)
    with open(log, "rb") as f:
        data = f.read()
        if args.lines is not None:
            data = b"".join(data.splitlines(keepends=True)[-args.lines :] if args.lines else [])
        sys.stdout.buffer.write(data)
        sys.stdout.flush()
        while args.follow:  # until Ctrl-C (main's KeyboardInterrupt), or the log is removed
            chunk = f.read()
            if chunk:
                sys.stdout.buffer.write(chunk)
                sys.stdout.flush()
            elif not log.exists():
                print(f"netlab: {log} was removed", file=sys.stderr)
                return 1
            else:
                time.sleep(0.2)
    return 0


def cmd_pingall(args: argparse.Namespace) -> int:
    record = lab_record(args.name, what="pingall")
    addresses = {  # the addresses in effect (sdfrd's own, with auto addressing)
        name: (kernel.addresses(r.ns, r.iface, f"reading {name}'s address") or [""])[0]
        for name, r in record.robots.items()
    }
    missing = [n for n, a in addresses.items() if not a]
    if missing:
        raise NetlabError(f"robots without an address yet: {', '.join(missing)}")
    linked = Topology.from_json(record.medium).links() if record.medium else None
    robots = list(record.robots)
    print(f"pingall: {len(robots)} robots, {args.count} pings per pair", flush=True)
    results = pingall.ping_all(
        {n: r.ns for n, r in record.robots.items()}, addresses, args.count, args.timeout
    )
    for line in pingall.matrix(robots, results, linked):
        print(line)
    verdict = pingall.judge(results, linked)
    print(pingall.summary(verdict))
    if linked is None:
        print("(the medium's links are not recorded: every pair was expected to answer)")
    for a, b in verdict.failed:
        print(f"FAIL {a} -> {b}: linked by the medium, no reply")
    return 0 if verdict.ok else 1
