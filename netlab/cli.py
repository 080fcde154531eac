"""The `netlab` command: bring labs up and down, look at them, run commands in robots.

    netlab up NAME --robots N | -t FILE [--runtime namespace|docker] [--seed S] [--radius R]
              [--spacing D] [--start]
    netlab down NAME
    netlab status [NAME]
    netlab exec NAME ROBOT -- CMD...
    netlab partition NAME GROUP GROUP...      (a group: r1,r2,...)
    netlab merge NAME
    netlab shape NAME ROBOT... [--loss %] [--delay MS] [--rate R] ... | --clear
    netlab run FILE|NAME [--runtime namespace|docker] [--runs DIR] [--quick] [--no-capture]
               [--no-report] [--lab NAME]
    netlab run --list
    netlab capture NAME ROBOT|medium --out FILE|- [--filter BPF] [--duration S]
    netlab report RUN_DIR
    netlab doctor

`up` leaves the lab running after the command exits; `down` removes it,
also when the program that made it died. Exit status 0 on success, 1 when
netlab could not do it (the message says why) or a scenario's check failed,
2 for a bad command line or scenario file, 3 when a scenario was skipped
(this sdfrd lacks an option it needs).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from netlab import cleanup, docker, kernel, manifest, naming
from netlab.capture import DEFAULT_BPF
from netlab.doctor import format_report, probe
from netlab.errors import LabNotFoundError, NetlabError, UnknownRobotError, missing_extra
from netlab.lab import Lab
from netlab.manifest import Manifest
from netlab.ranges import UnitDisc
from netlab.robots import RUNTIMES
from sdfr import version_text

if TYPE_CHECKING:
    from netlab.scenario import Scenario


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


def _group(text: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise argparse.ArgumentTypeError(f"a group is robot names joined by commas, got {text!r}")
    return names


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds, got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be above 0 seconds, got {text}")
    return value


def _runtime_options(p: argparse.ArgumentParser, default: str | None) -> None:
    p.add_argument(
        "--runtime",
        choices=RUNTIMES,
        default=default,
        help="robots as network namespaces, or as docker containers of the robot image "
        f"(default: {default or 'the scenario says, else namespace'})",
    )
    p.add_argument(
        "--image",
        default=docker.DEFAULT_IMAGE,
        help=f"the robot image of --runtime docker (default {docker.DEFAULT_IMAGE}; "
        "`make image` builds it)",
    )


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="netlab",
        description="A fleet of SDfR robots on this machine: one network namespace per robot "
        "(a namespace, or a container's), running the real sdfrd, on a shared medium. "
        "Needs root.",
    )
    p.add_argument("--version", action="version", version=version_text("netlab"))
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    up = sub.add_parser(
        "up",
        help="create a lab and leave it running",
        description="Create a lab and leave it running: N robots r1..rN, or the robots, kinds, "
        "positions and medium of a topology file (a scenario file whose steps only lay out the "
        "medium: partition, merge, move, quality, shape). Flags override the file.",
    )
    up.add_argument("name", type=_lab_name, metavar="NAME", help="lab name: 1-8 of a-z 0-9")
    how = up.add_mutually_exclusive_group(required=True)
    how.add_argument("--robots", type=_positive_int, metavar="N", help="robots r1..rN")
    how.add_argument(
        "-t", "--topology", metavar="FILE", help="a topology (or scenario) file: see above"
    )
    _runtime_options(up, None)
    up.add_argument("--seed", type=int, help="seed of the robots' MACs (default 0)")
    up.add_argument("--radius", type=_metres, help="radio range in metres (default 50)")
    up.add_argument(
        "--spacing",
        type=_metres,
        help="robots stand on a line this many metres apart (default 0: all in one spot)",
    )
    up.add_argument("--fleet", type=int, help="fleet id 0-255 (default 1)")
    up.add_argument("--workdir", help="where daemons keep state and logs (default: a new /tmp dir)")
    up.add_argument("--start", action="store_true", help="start sdfrd on every robot")
    up.add_argument(
        "--beacon-interval",
        type=float,
        default=None,
        metavar="S",
        help="sdfrd's beacon interval with --start (default: the topology file's, else sdfrd's)",
    )

    part = sub.add_parser(
        "partition", help="cut a running lab's medium into groups (robots in none: one more)"
    )
    part.add_argument("name", type=_lab_name, metavar="NAME")
    part.add_argument("groups", nargs="+", type=_group, metavar="GROUP", help="r1,r2,...")

    merge = sub.add_parser("merge", help="end a running lab's partition")
    merge.add_argument("name", type=_lab_name, metavar="NAME")

    shp = sub.add_parser(
        "shape",
        help="shape robots' links in a running lab (both directions)",
        description="Shape each robot's link, both directions: netem where the kernel has it; "
        "without netem, loss goes through the medium and rate through tbf, and delay, jitter, "
        "duplicate, reorder and corrupt are refused naming the missing module. The new shape "
        "replaces the robot's old one; --clear removes it.",
    )
    shp.add_argument("name", type=_lab_name, metavar="NAME")
    shp.add_argument("robots", nargs="+", metavar="ROBOT")
    shp.add_argument("--delay", type=float, metavar="MS", help="delay in ms (default 0)")
    shp.add_argument("--jitter", type=float, metavar="MS", help="jitter in ms, with a delay")
    for what in ("loss", "duplicate", "reorder", "corrupt"):
        shp.add_argument(f"--{what}", type=float, metavar="%", help=f"{what} in %% (default 0)")
    shp.add_argument("--rate", metavar="R", help="rate in bit/s or like 1mbit (default none)")
    shp.add_argument("--clear", action="store_true", help="remove all shaping")

    down = sub.add_parser("down", help="stop and remove a lab (also one whose runner died)")
    down.add_argument("name", type=_lab_name, metavar="NAME")

    status = sub.add_parser("status", help="labs, their robots, namespaces and daemons")
    status.add_argument("name", type=_lab_name, nargs="?", metavar="NAME")
    status.add_argument("--json", action="store_true", help="machine-readable output")

    ex = sub.add_parser(
        "exec", help="run a command inside a robot (its namespace, or its container)"
    )
    ex.add_argument("name", type=_lab_name, metavar="NAME")
    ex.add_argument("robot", metavar="ROBOT")
    ex.add_argument("cmd", nargs=argparse.REMAINDER, metavar="-- CMD...")

    rn = sub.add_parser(
        "run",
        help="run a scenario (a TOML file or a bundled one) on a new lab",
        description="Run a scenario on a new lab, with captures, progress and a report in a "
        "run folder. Exit status 0 when every check passed, 1 when one failed, 3 when skipped.",
    )
    rn.add_argument(
        "scenario",
        nargs="?",
        metavar="FILE|NAME",
        help="scenario file, or the name of a bundled scenario (--list shows them)",
    )
    rn.add_argument("--list", action="store_true", help="list the bundled scenarios")
    _runtime_options(rn, None)
    rn.add_argument(
        "--runs", default="runs", metavar="DIR", help="where run folders go (default runs/)"
    )
    rn.add_argument(
        "--quick",
        action="store_true",
        help="short durations for mobility and sleep steps that have one (CI)",
    )
    rn.add_argument("--no-capture", action="store_true", help="no tcpdump")
    rn.add_argument(
        "--no-report", action="store_true", help="no report.json and plots (run.json still)"
    )
    rn.add_argument("--lab", type=_lab_name, metavar="NAME", help="lab name (default: made unique)")

    cap = sub.add_parser("capture", help="capture a robot's (or the medium's) traffic to pcap")
    cap.add_argument("name", type=_lab_name, metavar="NAME", help="a lab brought up with up")
    cap.add_argument("target", metavar="ROBOT|medium")
    cap.add_argument(
        "--out",
        required=True,
        metavar="FILE",
        help="pcap to write; - streams it to standard output "
        "(`netlab capture LAB r1 --out - | wireshark -k -i -`)",
    )
    cap.add_argument(
        "--filter",
        default=DEFAULT_BPF,
        metavar="BPF",
        help=f"what to capture, a tcpdump filter (default {DEFAULT_BPF!r}; '' for everything)",
    )
    cap.add_argument(
        "--duration", type=_seconds, metavar="S", help="stop after S seconds (default: at Ctrl-C)"
    )

    rep = sub.add_parser("report", help="write a run folder's report.json and plots again")
    rep.add_argument("run_dir", metavar="RUN_DIR")

    sub.add_parser("doctor", help="what this kernel supports, and what follows")
    return p


def _topology(args: argparse.Namespace) -> Scenario:
    """The lab `up` makes, as a scenario with no timeline: the file's, flags overriding it."""
    from netlab import scenario

    flags = {
        key: getattr(args, key)
        for key in ("seed", "fleet", "radius", "spacing", "runtime")
        if getattr(args, key) is not None
    }
    try:
        if args.topology is None:
            return scenario.Scenario("up", robots=args.robots, **{"spacing": 0.0, **flags})
        sc = scenario.load(args.topology)
        scenario.check_layout(sc)
        return replace(sc, **flags)
    except scenario.ScenarioError as exc:
        raise NetlabError(str(exc)) from None


def cmd_up(args: argparse.Namespace) -> int:
    from netlab import scenario

    sc = _topology(args)
    lab = Lab(
        args.name,
        seed=sc.seed,
        fleet=sc.fleet,
        workdir=Path(args.workdir) if args.workdir else None,
        range_model=UnitDisc(sc.radius),
        addressing=sc.addressing,
        runtime=sc.runtime,
        image=args.image,
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
            t1 = time.monotonic()
            opts: dict[str, Any] = dict(sc.sdfrd)
            beacon = args.beacon_interval or (sc.beacon if args.topology else None)
            if beacon is not None:
                opts["beacon_interval"] = beacon
            lab.start_all(timeout=max(60.0, 2.0 * n), **opts)
            print(f"sdfrd healthy on {n} robots in {time.monotonic() - t1:.2f} s")
    except BaseException:
        lab.down()
        raise
    print(f"workdir {lab.workdir}")
    print(f"`netlab status {args.name}` shows it; `netlab down {args.name}` removes it")
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
    links = lab.links()
    pairs = {frozenset(p) for p in links}
    return f"{len(pairs)} linked pairs of {len(lab.robots)} robots"


def cmd_partition(args: argparse.Namespace) -> int:
    with _attached(args.name) as lab:
        lab.partition(args.groups)
        rest = [r for r in lab.robots if not any(r in g for g in args.groups)]
        groups = [",".join(g) for g in args.groups] + ([",".join(rest)] if rest else [])
        print(f"lab {args.name}: partition {' | '.join(groups)}; {_links_summary(lab)}")
    return 0


def cmd_merge(args: argparse.Namespace) -> int:
    with _attached(args.name) as lab:
        lab.merge()
        print(f"lab {args.name}: merged; {_links_summary(lab)}")
    return 0


SHAPE_PARAMS = ("delay", "jitter", "loss", "duplicate", "reorder", "corrupt", "rate")


def cmd_shape(args: argparse.Namespace) -> int:
    params = {k: getattr(args, k) for k in SHAPE_PARAMS if getattr(args, k) is not None}
    if args.clear == bool(params):
        raise NetlabError("shape: give shaping parameters (--loss, --delay, ...) or --clear")
    with _attached(args.name) as lab:
        for robot in args.robots:
            lab.robot(robot)  # all known before any is shaped
        for robot in args.robots:
            shape = lab.shape(robot, **params)
            what = ", ".join(f"{k} {v}" for k, v in dataclasses.asdict(shape).items() if v)
            print(f"lab {args.name}: {robot}: {what or 'no shaping'}")
    return 0


def cmd_down(args: argparse.Namespace) -> int:
    result = cleanup.sweep(args.name, manifest.load(args.name))
    if result.empty:
        print(f"no lab {args.name}: nothing to remove")
        return 0
    parts = [f"{len(result.namespaces)} namespaces"]
    if result.containers:
        parts.append(f"{len(result.containers)} containers")
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
        "runner": {"pid": record.runner_pid, "alive": runner_alive, "detached": record.detached},
        "workdir": record.workdir,
        "medium": naming.air_ns(record.name) in present,
        "robots": {
            name: {
                "runtime": r.runtime,
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
        if runner["alive"]:
            who = f"run by pid {runner['pid']}"
        elif runner["detached"]:
            who = "left up (netlab up)"  # its runner's exit is how `up` ends: no failure
        else:
            who = f"its runner (pid {runner['pid']}) DIED: `netlab down {lab['name']}`"
        print(f"lab {lab['name']}: {len(lab['robots'])} robots, {who}, workdir {lab['workdir']}")
        if not lab["medium"]:
            print("  medium namespace MISSING")
        for name, r in lab["robots"].items():
            ns = "ok" if r["present"] else "MISSING"
            daemon = f"sdfrd pid {r['sdfrd']}" if r["sdfrd"] else "no sdfrd"
            kind = "container" if r["runtime"] == "docker" else "namespace"
            print(f"  {name:<12} {r['address']:<16} {r['mac']}  {kind} {ns}  {daemon}")
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
    if robot.runtime == "docker":
        argv = docker.exec_argv(robot.ns, cmd, stdin=True, tty=sys.stdin.isatty())
    else:
        argv = kernel.ns_argv(robot.ns, cmd)
    sys.stdout.flush()
    os.execvp(argv[0], argv)


EXIT_FAILED = 1
EXIT_BAD_SCENARIO = 2
EXIT_SKIPPED = 3


def cmd_run(args: argparse.Namespace) -> int:
    from netlab import scenario

    if args.list:
        print(f"{'scenario':18} {'robots':>6} {'beacon':>7} {'takes':>14} {'--quick':>14}  about")
        for name, path in scenario.bundled().items():
            try:
                sc = scenario.load(path)
            except scenario.ScenarioError as exc:
                print(f"{name:18} (invalid: {exc})")
                continue
            full, quick = _span(*sc.timeline()), _span(*sc.timeline(quick=True))
            n = len(sc.names)
            print(f"{name:18} {n:>6} {sc.beacon:>6g}s {full:>14} {quick:>14}  {sc.description}")
        print("takes: the steps' own time, and at most (every check waiting out its deadline);")
        print("starting daemons and taking the lab down add seconds")
        return 0
    if not args.scenario:
        raise NetlabError("run: give a scenario file or a bundled scenario's name (--list)")
    try:
        sc = scenario.load(scenario.find(args.scenario))
    except scenario.ScenarioError as exc:
        print(f"netlab: {exc}", file=sys.stderr)
        return EXIT_BAD_SCENARIO
    result = scenario.run(
        sc,
        lab_name=args.lab,
        runs=Path(args.runs),
        quick=args.quick,
        capture="none" if args.no_capture else None,
        report=not args.no_report,
        runtime=args.runtime,
        image=args.image,
    )
    if result.status == "skipped":
        return EXIT_SKIPPED
    return 0 if result.ok else EXIT_FAILED


def _span(least: float, most: float) -> str:
    def fmt(s: float) -> str:
        return (
            f"{s / 60:.0f} min" if s >= 600 else f"{s / 60:.1f} min" if s >= 120 else f"{s:.0f} s"
        )

    low, high = fmt(least), fmt(most)
    return low if low == high else f"{low}-{high}"


def cmd_capture(args: argparse.Namespace) -> int:
    from netlab.capture import Capture

    record = manifest.load(args.name)
    if record is None:
        raise LabNotFoundError(f"no lab {args.name} is up (`netlab status` lists labs)")
    if args.target == "medium":
        ns, iface = naming.air_ns(args.name), naming.BRIDGE
    else:
        robot = record.robots.get(args.target)
        if robot is None:
            raise UnknownRobotError(
                f"lab {args.name} has no robot {args.target!r} (robots: "
                f"{', '.join(record.robots)}; or medium)"
            )
        ns, iface = robot.ns, naming.ROBOT_IFACE
    if args.out == "-":
        return _stream(Capture(ns, iface, Path("-"), bpf=args.filter), args.duration)
    out = Path(args.out)
    cap = Capture(ns, iface, out, bpf=args.filter, label=args.target)
    cap.start()
    until = f"for {args.duration:g} s" if args.duration else "until Ctrl-C"
    print(f"capturing {iface} of {args.target} in lab {args.name} to {out} {until}", flush=True)
    try:
        if args.duration:
            time.sleep(args.duration)
        else:
            while cap.running:
                time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        stats = cap.stop()
    print(
        f"{out}: {stats.captured if stats.captured is not None else '?'} frames captured"
        + (f", {stats.dropped} dropped by the kernel" if stats.dropped else "")
    )
    return 0


def _stream(cap: Any, duration: float | None) -> int:
    """tcpdump writing the pcap to our standard output (a pipe into Wireshark) until Ctrl-C,
    the reader's end, or `duration`; its messages go to standard error."""
    sys.stdout.flush()
    proc = subprocess.Popen(cap.argv(), stdin=subprocess.DEVNULL, start_new_session=True)
    try:
        proc.wait(timeout=duration)
    except subprocess.TimeoutExpired:
        pass
    except KeyboardInterrupt:
        pass
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)  # tcpdump ends the stream with whole records
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from netlab.scenario import rebuild_report

    run_dir = Path(args.run_dir)
    try:
        report = rebuild_report(run_dir)
    except ImportError as exc:
        raise missing_extra(exc, "netlab report") from None
    robots = report["traffic"]["robots"]
    print(
        f"{run_dir / 'report.json'}: {len(robots)} robots over "
        f"{report['window']['duration_s']:.1f} s"
    )
    for robot, t in robots.items():
        print(
            f"  {robot:12} TX {t['tx_kB']['payload']:8.1f} kB  RX {t['rx_kB']['payload']:8.1f} kB"
            "  (UDP payload)"
        )
    if "agreement" in report:
        print(f"  agreement with the medium: mean {report['agreement']['mean']:.1%}")
    print("plots: " + ", ".join(sorted(report["plots"].values())))
    return 0


def cmd_doctor(args: argparse.Namespace) -> int:
    caps = probe(docker=True)
    print(format_report(caps))
    return 0 if caps.lab else 1


COMMANDS = {
    "up": cmd_up,
    "down": cmd_down,
    "status": cmd_status,
    "exec": cmd_exec,
    "partition": cmd_partition,
    "merge": cmd_merge,
    "shape": cmd_shape,
    "run": cmd_run,
    "capture": cmd_capture,
    "report": cmd_report,
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
    except BrokenPipeError:
        # The reader of our output went away (`netlab ... | head`): not an error of ours.
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    raise SystemExit(main())
