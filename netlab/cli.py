"""The `netlab` command: bring labs up and down, look at them, run commands in robots.

    netlab up NAME --robots N | -t FILE [--start] [--runtime namespace|docker] [--seed S]
              [--radius R] [--spacing D] [--fleet F] [--workdir DIR] [--beacon-interval S]
    netlab down NAME [--cleanup]
    netlab status [NAME] [--json]
    netlab exec NAME ROBOT -- CMD...  |  netlab exec --all NAME -- CMD...
    netlab logs NAME|DIR ROBOT [-f] [-n N]
    netlab pingall NAME [--count N] [--timeout S]
    netlab partition NAME GROUP GROUP...      (a group: r1,r2,...)
    netlab merge NAME
    netlab shape NAME ROBOT... [--loss %] [--delay MS] [--rate R] ... | --clear
    netlab run FILE|NAME [--runtime namespace|docker] [--runs DIR] [--quick] [--no-capture]
               [--no-report] [--lab NAME]
    netlab run --list
    netlab capture NAME ROBOT|medium --out FILE|- [--filter BPF] [--duration S]
    netlab report RUN_DIR
    netlab doctor

`up` leaves the lab running after the command exits; `down` removes it (also when the
program that made it died) and keeps its folder of daemon logs unless --cleanup.  Exit
status 0 on success, 1 when netlab could not do it (the message says why), a scenario's
check failed or pingall found a linked pair silent, 2 for a bad command line or scenario
file, 3 when a scenario was skipped (this sdfrd lacks an option it needs); `exec` exits
with the command's status (with --all, the worst).  The reference is docs/netlab-cli.md.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from netlab import docker, naming
from netlab.capture import DEFAULT_BPF
from netlab.doctor import format_report, probe
from netlab.errors import NetlabError, UnknownRobotError, missing_extra
from netlab.labcli import (
    cmd_down,
    cmd_exec,
    cmd_logs,
    cmd_merge,
    cmd_partition,
    cmd_pingall,
    cmd_shape,
    cmd_status,
    cmd_up,
    host_list,
    lab_record,
)
from netlab.robots import AIRS, RUNTIMES
from sdfr import version_text
from sdfr.argparsing import HintingParser
from sdfr.hints import did_you_mean

NAME_HELP = "the lab's name (`netlab status` lists them)"


def _lab_name(text: str) -> str:
    try:
        return naming.check_lab_name(text)
    except NetlabError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _whole(text: str, least: int) -> int:
    """`text` as a whole number of at least `least`, else a usage error saying which."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < least:
        bound = "0 or more" if least == 0 else f"at least {least}"
        raise argparse.ArgumentTypeError(f"must be {bound}, got {value}")
    return value


def _positive_int(text: str) -> int:
    return _whole(text, 1)


def _count(text: str) -> int:
    return _whole(text, 0)


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


def _hosts_options(p: argparse.ArgumentParser, hosts_help: str) -> None:
    p.add_argument("--hosts", metavar="H1,H2,...", help=hosts_help)
    p.add_argument("--ssh-config", type=Path, help="ssh's configuration file (default: ssh's)")
    p.add_argument("--host-python", default="python3", metavar="PATH",
                   help="the interpreter with netlab on the hosts (default: python3)")  # fmt: skip


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
    p.add_argument(
        "--medium",
        choices=AIRS,
        default=None,
        help="what robots meet on: a wired bridge, or 802.11 radios (mac80211_hwsim; each "
        "sdfrd joins the fleet's WiFi) (default: the scenario says, else wired)",
    )


def _name(p: argparse.ArgumentParser, what: str = NAME_HELP) -> None:
    p.add_argument("name", type=_lab_name, metavar="NAME", help=what)


def build_parser() -> argparse.ArgumentParser:
    p = HintingParser(
        prog="netlab",
        description="A fleet of SDfR robots on this machine: one network namespace per robot "
        "(a namespace, or a container's), running the real sdfrd, on a shared medium. "
        "Needs root.",
        epilog="`netlab COMMAND --help` describes a command; docs/netlab-cli.md is the reference.",
    )
    p.add_argument("--version", action="version", version=version_text("netlab"))
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    up = sub.add_parser(
        "up",
        help="create a lab and leave it running",
        description="Create a lab and leave it running: N robots r1..rN, or the robots, kinds, "
        "positions and medium of a topology file (a scenario file whose steps only lay out the "
        "medium: partition, merge, move, quality, shape). Flags override the file. Without "
        "--start no daemon runs (the command says so).",
    )
    _name(up, "the new lab's name: 1-8 of a-z 0-9")
    how = up.add_mutually_exclusive_group(required=True)
    how.add_argument("--robots", type=_positive_int, metavar="N", help="robots r1..rN")
    how.add_argument(
        "-t",
        "--topology",
        metavar="FILE",
        help="a topology (or scenario) file, or a bundled scenario's name: see above",
    )
    up.add_argument("--start", action="store_true", help="start sdfrd on every robot")
    _runtime_options(up, None)
    up.add_argument("--seed", type=int, help="seed of the robots' MACs (default 0)")
    up.add_argument("--radius", type=_metres, help="radio range in metres (default 50)")
    up.add_argument(
        "--spacing",
        type=_metres,
        help="robots stand on a line this many metres apart (default 0: all in one spot)",
    )
    up.add_argument("--fleet", type=int, help="fleet id 0-255 (default 1)")
    up.add_argument(
        "--workdir",
        metavar="DIR",
        help="the lab's folder: daemon logs and state (default: a new /tmp/netlab-NAME-* dir)",
    )
    up.add_argument(
        "--beacon-interval",
        type=float,
        default=None,
        metavar="S",
        help="sdfrd's beacon interval with --start (default: the topology file's, else sdfrd's)",
    )
    _hosts_options(up, "spread the lab over these hosts (ssh destinations) instead of the "
                   "topology's [hosts] or this machine (docs/hosts.md)")  # fmt: skip

    down = sub.add_parser(
        "down",
        help="stop and remove a lab (also one whose runner died)",
        description="Stop the lab's processes and remove its namespaces, containers and "
        "manifest. Its folder (daemon logs and state) is kept, and its path printed, unless "
        "--cleanup.",
    )
    _name(down)
    down.add_argument(
        "--cleanup", action="store_true", help="also remove the lab's folder (daemon logs, state)"
    )

    status = sub.add_parser(
        "status",
        help="show labs: robots, daemons, the medium's partition and shaping",
        description="Each lab: who runs it, its folder, the medium in effect (partition, pair "
        "loss, links up), and a table of its robots (address, MAC, kind, namespace, sdfrd, how "
        "many robots each hears, its link shaping).",
    )
    status.add_argument(
        "name", type=_lab_name, nargs="?", metavar="NAME", help="one lab (default: every lab)"
    )
    status.add_argument("--json", action="store_true", help="machine-readable output")

    ex = sub.add_parser(
        "exec",
        usage="netlab exec NAME ROBOT -- CMD...\n       netlab exec --all NAME -- CMD...",
        help="run a command in a robot, or in every robot (--all)",
        description="Run CMD inside the robot (its namespace, or its container) with its "
        "exit status; with --all in every robot at once, each output line prefixed with the "
        "robot's name, exit status the worst of them.",
    )
    _name(ex)
    ex.add_argument("--all", action="store_true", help="every robot of the lab (no ROBOT)")
    ex.add_argument(
        "cmd",
        nargs=argparse.REMAINDER,
        metavar="ROBOT -- CMD...",
        help="the robot (not with --all), then the command after --",
    )

    logs = sub.add_parser(
        "logs",
        help="print a robot's daemon log (-f: follow it)",
        description="Print the log of the robot's sdfrd, from a lab that is up, or from a "
        "lab's folder kept by `netlab down`.",
    )
    logs.add_argument(
        "lab", metavar="NAME|DIR", help="a lab that is up, or the folder `netlab down` kept"
    )
    logs.add_argument("robot", metavar="ROBOT", help="the robot, e.g. r1")
    logs.add_argument(
        "-f", "--follow", action="store_true", help="keep printing what is added (Ctrl-C ends)"
    )
    logs.add_argument(
        "-n", "--lines", type=_count, metavar="N", help="only the last N lines (default: all)"
    )

    pa = sub.add_parser(
        "pingall",
        help="ping every robot from every other: a loss matrix",
        description="Every robot pings every other over the medium (all at once) and a matrix "
        "of loss is printed: a pair the medium links must answer, one it cuts should not. Exit "
        "status 1 if a linked pair did not answer.",
    )
    _name(pa)
    pa.add_argument(
        "--count", type=_positive_int, default=3, metavar="N", help="pings per pair (default 3)"
    )
    pa.add_argument(
        "--timeout",
        type=_seconds,
        default=1.0,
        metavar="S",
        help="seconds to wait for the last reply (default 1)",
    )

    part = sub.add_parser(
        "partition",
        help="cut a running lab's medium into groups",
        description="Cut every link between the groups; the robots in no group form one more "
        "group. Ends the previous partition.",
    )
    _name(part)
    part.add_argument(
        "groups",
        nargs="+",
        type=_group,
        metavar="GROUP",
        help="robots joined by commas, e.g. r1,r2 r3,r4",
    )

    merge = sub.add_parser(
        "merge",
        help="end a running lab's partition",
        description="End the partition: the range model alone decides the links again.",
    )
    _name(merge)

    shp = sub.add_parser(
        "shape",
        help="shape robots' links in a running lab (both directions)",
        description="Shape each robot's link, both directions: netem where the kernel has it; "
        "without netem, loss goes through the medium and rate through tbf, and delay, jitter, "
        "duplicate, reorder and corrupt are refused naming the missing module. The new shape "
        "replaces the robot's old one; --clear removes it.",
    )
    _name(shp)
    shp.add_argument("robots", nargs="+", metavar="ROBOT", help="the robots to shape")
    shp.add_argument("--delay", type=float, metavar="MS", help="delay in ms (default 0)")
    shp.add_argument("--jitter", type=float, metavar="MS", help="jitter in ms, with a delay")
    for what in ("loss", "duplicate", "reorder", "corrupt"):
        shp.add_argument(f"--{what}", type=float, metavar="%", help=f"{what} in %% (default 0)")
    shp.add_argument("--rate", metavar="R", help="rate in bit/s or like 1mbit (default none)")
    shp.add_argument("--clear", action="store_true", help="remove all shaping")

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
    rn.add_argument(
        "--no-plots",
        action="store_true",
        help="report.json without its PNGs (faster; `netlab report RUN` draws them later)",
    )
    rn.add_argument("--lab", type=_lab_name, metavar="NAME", help="lab name (default: made unique)")
    _hosts_options(
        rn,
        "run the lab across these hosts (ssh destinations: aliases or user@address), over "
        "ssh, instead of the scenario's [hosts] or this machine; robots the scenario does "
        "not place on one of them are spread over them",
    )

    cap = sub.add_parser("capture", help="capture a robot's (or the medium's) traffic to pcap")
    _name(cap, "a lab brought up with `netlab up`")
    cap.add_argument("target", metavar="ROBOT|medium", help="a robot, or the medium's bridge")
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

    rep = sub.add_parser(
        "report",
        help="write a run folder's report.json and plots again",
        description="Read a run folder's run.json and pcaps; write report.json, the plots "
        "and report.html again.",
    )
    rep.add_argument("run_dir", metavar="RUN_DIR", help="a folder `netlab run` wrote")

    doc = sub.add_parser(
        "doctor",
        help="check what this kernel supports, and what follows",
        description="Try each kernel feature netlab uses in a throwaway namespace and say "
        "what follows from what is missing. Exit status 1 when no lab can run here. With "
        "--hosts, check each host of a lab across machines over ssh instead.",
    )
    _hosts_options(
        doc,
        "ssh destinations (aliases or user@address) to check: reachable, root, the same "
        "netlab version, iproute2/nftables/tcpdump, VXLAN; and each one's clock offset",
    )
    return p


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
    backend = None
    if args.hosts or sc.hosts:
        from netlab.spanlab import scenario_backend

        backend = scenario_backend(
            sc, hosts=host_list(args.hosts), ssh_config=args.ssh_config, python=args.host_python
        )
    result = scenario.run(
        sc,
        backend=backend,
        lab_name=args.lab,
        runs=Path(args.runs),
        quick=args.quick,
        capture="none" if args.no_capture else None,
        report=not args.no_report,
        plots=not args.no_plots,
        runtime=args.runtime,
        image=args.image,
        medium=args.medium,
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

    robot = None if args.target == "medium" else args.target
    record = lab_record(args.name, robot, "capture")
    if args.target == "medium":
        ns, iface = naming.air_ns(args.name), naming.BRIDGE
    else:
        robot = record.robots.get(args.target)
        if robot is None:
            raise UnknownRobotError(
                f"lab {args.name} has no robot {args.target!r}"
                f"{did_you_mean(args.target, [*record.robots, 'medium'])} (robots: "
                f"{', '.join(record.robots)}; or medium)"
            )
        ns, iface = robot.ns, robot.iface
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
    if args.hosts:
        from netlab.hosts import main_doctor

        return main_doctor(host_list(args.hosts), args.ssh_config, args.host_python)
    caps = probe(docker=True)
    print(format_report(caps))
    return 0 if caps.lab else 1


COMMANDS = {
    "up": cmd_up,
    "down": cmd_down,
    "status": cmd_status,
    "exec": cmd_exec,
    "logs": cmd_logs,
    "pingall": cmd_pingall,
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
