"""The engine: one run of a scenario against a lab, in the backend's time.

`run()` makes the run folder and a `Run`; `Run.execute` brings the lab up, starts the captures
and the observer, walks the timeline (each action step through `actions.ACTIONS`, each check
through `judges`), takes everything down, and writes the run folder.  It reads time only
through `backend.clock`, so a fake lab and a `netlab.clock.VirtualClock` run a whole scenario
in an instant.
"""

from __future__ import annotations

import contextlib
import shutil
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from netlab import naming, procstat
from netlab.analysis import count_updates
from netlab.docker import DEFAULT_IMAGE
from netlab.errors import NetlabError, missing_extra
from netlab.observe import Observer, Probe
from netlab.pcap import read_run
from netlab.ranges import UnitDisc
from netlab.samples import Sample
from netlab.scenario.actions import ACTIONS
from netlab.scenario.backend import SAMPLE_TIMEOUT, STEP_TIMEOUT, Backend, LabSpec
from netlab.scenario.conditions import Agreement, Resources
from netlab.scenario.context import CheckContext, Fleet, History, StepContext
from netlab.scenario.judges import AFTER_POLL, EVALUATORS, JUDGES
from netlab.scenario.model import Scenario, reference, step_ref
from netlab.scenario.results import CheckResult, RunResult
from netlab.scenario.runfolder import new_run_dir, save_run, write_report
from netlab.scenario.spec import Bad, Span, seconds
from netlab.scenario.steps import Check
from netlab.scenario.topology import add_robots
from netlab.truth import TruthLog
from sdfr.errors import ApiError

if TYPE_CHECKING:
    from netlab.capture import Capture

PRODUCT_BEACON = 10.0


class Run:
    """One run of a scenario: the lab, the captures, the observer, the timeline, the report.

    Actions and judges see none of it: each gets a `StepContext` or `CheckContext`
    (`netlab.scenario.context`) with the parts it uses.
    """

    def __init__(
        self,
        sc: Scenario,
        backend: Backend,
        run_dir: Path,
        spec: LabSpec,
        quick: bool,
        say: Callable[[str], None],
    ) -> None:
        self.sc = sc
        self.backend = backend
        self.clock = backend.clock
        self.run_dir = run_dir
        self.quick = quick
        self._say = say
        self.lab = backend.make_lab(spec)
        self.truth = TruthLog(clock=self.clock.time)
        self.fleet = Fleet(sc.selectors(), self.lab, self.truth)
        self.history = History(sc.steps, action_wall=self.clock.time())
        self.checks: list[CheckResult] = []
        self.error: str | None = None
        self.t0 = self.clock.monotonic()
        self.event = self.t0  # end of the last action step
        self.samples: list[Sample] = []
        self.captured = False
        self.wall = (self.clock.time(), self.clock.time())
        #: Steps whose window a resources check measures.
        self.measured = {
            reference(sc.steps, i, s.condition.over)
            for i, s in enumerate(sc.steps, 1)
            if isinstance(s, Check) and isinstance(s.condition, Resources)
        }

    def say(self, text: str) -> None:
        self._say(f"  {self.elapsed():7.2f} s  {text}")

    def elapsed(self) -> float:
        """Seconds since the run began."""
        return self.clock.monotonic() - self.t0

    def seconds(self, span: Span) -> float:
        return seconds(span, self.sc.beacon)

    # -- the run -------------------------------------------------------------------------------

    def execute(self, *, report: bool, plots: bool = True) -> RunResult:
        start_wall = self.clock.time()
        self.t0 = self.clock.monotonic()
        captures: list[Capture] = []
        probe: Probe | None = None
        observer: Observer | None = None
        try:
            self.lab.up()
        except NetlabError as exc:
            self.say(f"ERROR {exc}")
            return RunResult(self.sc.name, "error", self.run_dir, error=str(exc))
        try:
            try:
                self._add_robots()
                captures = self._start_captures()
                probe = Probe(lambda r: self.backend.connect(self.lab, r, STEP_TIMEOUT))
                observer = Observer(
                    Probe(lambda r: self.backend.connect(self.lab, r, SAMPLE_TIMEOUT)),
                    self.truth,
                    self.sc.sample,
                    clock=self.clock,
                ).start()
                self._timeline(probe, observer)
            finally:
                self._teardown(captures, probe, observer)
        except (NetlabError, ApiError) as exc:
            self.error = self.error or f"{exc}{self._ended_unasked()}"
            self.say(f"ERROR {exc}")
        self.wall = (start_wall, self.clock.time())
        failed = any(c.ok is False for c in self.checks)
        result = RunResult(
            self.sc.name,
            "error" if self.error else "failed" if failed else "passed",
            self.run_dir,
            self.checks,
            error=self.error,
            robots=len(self.sc.names),
            beacon=self.sc.beacon,
            duration=self.elapsed(),
        )
        self._finish(result, report, plots)
        return result

    def _add_robots(self) -> None:
        t = self.clock.monotonic()
        add_robots(self.lab, self.sc)
        self.fleet.record_truth()
        took = self.clock.monotonic() - t
        n = len(self.sc.names)
        where = getattr(self.lab, "where", "on one medium")  # a lab across hosts says which
        self.say(f"lab {self.lab.name} up: {n} robots {where} in {took:.2f} s")

    def _start_captures(self) -> list[Capture]:
        mode = self.sc.capture
        if mode == "none":
            return []
        across = getattr(self.lab, "start_captures", None)
        if across is not None:  # a lab across hosts: tcpdumps on each, fetched at the end
            t = self.clock.monotonic()
            n = across(mode, self.sc.names)
            self.captured = True
            took = self.clock.monotonic() - t
            self.say(f"capturing on every host ({n} tcpdumps, {took:.2f} s)")
            return []
        from netlab.capture import Capture, air_monitor, start_all

        caps: list[Capture] = []
        if mode in ("all", "medium") and self.sc.medium == "radio":
            # Every 802.11 frame, management, control and EAPOL too: what the air carried.
            pcap = self.run_dir / "air.pcap"
            caps.append(Capture(None, air_monitor(), pcap, label="air", bpf=""))
        elif mode in ("all", "medium"):
            pcap = self.run_dir / "medium.pcap"
            caps.append(Capture(self.lab.medium.ns, naming.BRIDGE, pcap, label="medium"))
        if mode in ("all", "robots"):
            caps += [
                Capture(
                    self.lab.robot(n).ns,
                    self.lab.robot(n).iface,
                    self.run_dir / f"{n}.pcap",
                    label=n,
                )
                for n in self.sc.names
            ]
        t = self.clock.monotonic()
        start_all(caps)
        self.captured = True
        what = {"all": "the medium and every robot", "robots": "every robot"}.get(mode, mode)
        took = self.clock.monotonic() - t
        self.say(f"capturing on {what} ({len(caps)} tcpdumps, {took:.2f} s)")
        return caps

    def _teardown(
        self, captures: list[Capture], probe: Probe | None, observer: Observer | None
    ) -> None:
        if observer is not None:
            self.samples = observer.stop()
        if probe is not None:
            probe.close()
        try:
            fetch = getattr(self.lab, "stop_captures", None)
            if self.captured and fetch is not None:
                for problem in fetch(self.run_dir):
                    self.say(f"warning: {problem}")
            if captures:
                from netlab.capture import CaptureError, stop_all

                try:
                    stop_all(captures)
                except CaptureError as exc:
                    self.say(f"warning: {exc}")
        finally:
            self._keep_logs()
            self.lab.down()

    def _keep_logs(self) -> None:
        logs = self.run_dir / "logs"
        stats = getattr(self.lab, "air_stats_file", None)  # a radio lab's medium, if it ran
        if self.sc.medium == "radio" and isinstance(stats, Path):
            for kept, copy in (
                (stats, "air-medium.json"),
                (stats.parent / "medium.log", "air-medium.log"),
            ):
                with contextlib.suppress(OSError):
                    if kept.exists():
                        logs.mkdir(exist_ok=True)
                        shutil.copyfile(kept, logs / copy)
        fetch = getattr(self.lab, "fetch_log", None)  # a lab across hosts: logs are there
        for name in self.sc.names:
            with contextlib.suppress(NetlabError, OSError):
                if fetch is not None:
                    text = fetch(name)
                    if isinstance(text, str):
                        logs.mkdir(exist_ok=True)
                        (logs / f"{name}.log").write_text(text)
                    continue
                src = self.lab.robot(name).log
                if src.exists():
                    logs.mkdir(exist_ok=True)
                    shutil.copyfile(src, logs / f"{name}.log")

    def _timeline(self, probe: Probe, observer: Observer) -> None:
        common = (self.sc, self.lab, self.clock, self.fleet, probe, self.truth, self.say)
        acting = StepContext(*common, quick=self.quick)
        judging = CheckContext(*common, observer, self.history, self.captured, self.t0)
        for i, step in enumerate(self.sc.steps, 1):
            wall = self.clock.time()
            try:
                if isinstance(step, Check):
                    ok = self._check(i, step, judging)
                else:
                    self.history.action_wall = wall
                    before = self._usage() if i in self.measured else None
                    self.say(ACTIONS[type(step)](acting, step))
                    self.event = self.clock.monotonic()
                    if before is not None:
                        self.history.usage[i] = (before, self._usage())
                    ok = True
            except (NetlabError, ApiError, Bad) as exc:
                self.error = f"{step_ref(i, step)}: {exc}{self._ended_unasked()}"
                self.say(f"ERROR {self.error}")
                return
            finally:
                self.history.windows[i] = (wall, self.clock.time())
            if not ok and isinstance(step, Check) and step.fatal:
                self.say(f"stopping: {step_ref(i, step)} failed and later steps rely on it")
                return

    def _ended_unasked(self) -> str:
        """For an error: the robots whose sdfrd ended though no step stopped it (a crash, or
        something else killed it), how, and where their logs are; empty if none."""
        ended = self.lab.daemons_ended()
        if not ended:
            return ""
        said = ", ".join(f"{name} ({how})" for name, how in sorted(ended.items()))
        return f"; sdfrd ended though no step stopped it on {said}: see logs/ in the run folder"

    def _usage(self) -> dict[str, procstat.Usage]:
        """A /proc reading of each running daemon's process tree (empty when the lab cannot
        tell its daemons' pids)."""
        across = getattr(self.lab, "usage", None)  # a lab across hosts reads on each host
        if across is not None:
            return dict(across(self.fleet.running))
        pid_of = getattr(self.lab, "daemon_pid", None)
        if pid_of is None:
            return {}
        kids = procstat.children()
        out: dict[str, procstat.Usage] = {}
        for name in self.fleet.running:
            pid = pid_of(name)
            if pid is not None:
                out[name] = procstat.Usage.read(procstat.tree(pid, kids))
        return out

    # -- checks --------------------------------------------------------------------------------

    def _check(self, index: int, step: Check, ctx: CheckContext) -> bool:
        cond = step.condition
        res = CheckResult(index, cond.kind, step.describe(), step.fatal)
        self.checks.append(res)
        judge = JUDGES.get(type(cond))
        if judge is not None:
            judge(ctx, index, cond, res)
        else:
            self._poll(step, res, ctx)
            after = AFTER_POLL.get(type(cond))
            if after is not None:
                after(ctx, cond, res)
        return res.ok is not False

    def _poll(self, step: Check, res: CheckResult, ctx: CheckContext) -> None:
        evaluate = EVALUATORS[type(step.condition)]
        within = self.seconds(step.within) if step.within is not None else 0.0
        during = self.seconds(step.during) if step.during is not None else None
        steady = self.seconds(step.steady) if step.steady is not None else 0.0
        res.deadline = within if step.within is not None else None
        res.during = during
        since = self.event
        period = min(0.1, max(0.02, within / 20))
        first = True
        late: list[str] = []  # what was wrong at the deadline
        stretch: float | None = None  # since when it has held without a break (steady)
        while True:
            problems = evaluate(ctx, step.condition)
            now = self.clock.monotonic()
            if steady and not problems and (stretch is not None or first or now - since <= within):
                stretch = now if stretch is None else stretch
                if now - stretch < steady:
                    first = False
                    self.clock.sleep(period)
                    continue
                res.took = stretch - since
                break
            stretch = None
            if not problems and not steady and (first or now - since <= within):
                # At a first look after the deadline (earlier checks took that long) it
                # holds, but since when is not known: say so.
                res.took = now - since
                if now - since > within:
                    res.detail = f"first looked at {now - since:.2f} s, after the deadline"
                break
            if now - since > within and not first:
                res.ok = False
                res.at = now - self.t0
                if problems:
                    res.detail = "; ".join(problems)
                else:
                    res.detail = f"held from {now - since:.2f} s; at the deadline: " + "; ".join(
                        late
                    )
                self.say(f"FAIL  {res.description}: not within {within:.2f} s: {res.detail}")
                return
            if now - since <= within:
                late = problems
            first = False
            self.clock.sleep(period)
        if during:
            held_from = self.clock.monotonic()
            end = held_from + during
            while self.clock.monotonic() < end:
                self.clock.sleep(min(period, max(0.0, end - self.clock.monotonic())))
                problems = evaluate(ctx, step.condition)
                if problems:
                    res.ok = False
                    res.at = self.elapsed()
                    held = self.clock.monotonic() - held_from
                    res.detail = f"held {held:.2f} of {during:g} s, then: " + "; ".join(problems)
                    self.say(f"FAIL  {res.description}: {res.detail}")
                    return
        res.ok = True
        res.at = self.elapsed()
        if step.within is None:
            res.took = None  # it had to hold from the first look: there is no "when"
            self.say(f"ok    {res.description}: held {during or 0:g} s")
        else:
            kept = f", held steady {steady:g} s" if steady else ""
            kept += f", then held {during:g} s" if during else ""
            note = f" ({res.detail})" if res.detail else ""
            self.say(
                f"ok    {res.description}: {res.took or 0.0:.2f} s (deadline {within:.2f} s)"
                f"{kept}{note}"
            )

    # -- after the run -------------------------------------------------------------------------

    def _finish(self, result: RunResult, report: bool, plots: bool) -> None:
        records = None
        if self.captured and (self.history.deferred or report):
            try:
                records = read_run(self.run_dir)
            except ImportError as exc:
                self.say(f"cannot read the captures: {missing_extra(exc, 'reading captures')}")
            except (NetlabError, OSError) as exc:
                self.say(f"cannot read the captures: {exc}")
        for res, cond, since, until in self.history.deferred:
            if records is None:
                res.detail = "captures could not be read: not judged"
                continue
            n = count_updates(records, since=since, until=until)
            res.ok = n <= cond.at_most
            res.detail = f"{n} Update datagrams in the window (at most {cond.at_most})"
            self._say(f"  {'ok   ' if res.ok else 'FAIL '} {res.description}: {res.detail}")
        if result.status == "passed" and any(c.ok is False for c in self.checks):
            result.status = "failed"
        lag = self._report_lag()
        meta = self._meta(result, lag)
        save_run(self.run_dir, meta, self.samples, self.truth.states())
        if report:
            try:
                result.report = write_report(
                    self.run_dir, records, self.samples, self.truth.states(), lag, meta, plots
                )
            except ImportError as exc:
                self._say(f"  report not written: {missing_extra(exc, 'the report')}")
            except (NetlabError, OSError, ValueError) as exc:
                self._say(f"  report not written: {exc}")
        self._say("")
        for line in result.summary():
            self._say(line)
        files = "no report"
        if result.report is not None:
            files = "report.json and plots" if plots else "report.json; no plots"
        kept = "pcaps, " if self.captured else ""
        self._say(f"run folder: {self.run_dir} ({files}; {kept}run.json, logs/)")

    def _agreement_check(self) -> Agreement | None:
        for step in self.sc.steps:
            if isinstance(step, Check) and isinstance(step.condition, Agreement):
                return step.condition
        return None

    def _report_lag(self) -> float:
        check = self._agreement_check()
        return self.seconds(check.lag) if check is not None else self.sc.beacon

    def _meta(self, result: RunResult, lag: float) -> dict[str, object]:
        steps = []
        for i, step in enumerate(self.sc.steps, 1):
            window = self.history.windows.get(i)
            steps.append(
                {
                    "step": i,
                    "kind": step.kind,
                    "label": step.label,
                    "start": window[0] if window else None,
                    "end": window[1] if window else None,
                }
            )
        return {
            "scenario": self.sc.name,
            "description": self.sc.description,
            "file": self.sc.source,
            "robots": len(self.sc.names),
            "runtime": self.sc.runtime,
            "medium": self.sc.medium,
            "air_medium": self.sc.air_medium if self.sc.medium == "radio" else None,
            "radios": getattr(self.lab, "radio_macs", {}) if self.sc.medium == "radio" else {},
            "beacon_interval_s": self.sc.beacon,
            "quick": self.quick,
            "status": result.status,
            "error": result.error,
            "start": self.wall[0],
            "end": self.wall[1],
            "agreement_lag_s": lag,
            "agreement_target": check.at_least if (check := self._agreement_check()) else None,
            "checks": [c.to_json() for c in self.checks],
            "steps": steps,
            # A lab across hosts: each host's robots and clock offset (None on one host).
            "hosts": getattr(self.lab, "hosts_meta", None),
            "span_readings": getattr(self.lab, "span_meta", None),
        }


# ---------------------------------------------------------------------------------------------
# Running


def default_lab_name() -> str:
    """'s' + this process + a counter (`naming.unique_lab_name`)."""
    return naming.unique_lab_name("s")


def missing_requirements(scenario: Scenario, flags: frozenset[str]) -> str | None:
    """Why this sdfrd cannot run the scenario (an option it lacks), or None."""
    missing = sorted(o for o in scenario.sdfrd_options() if o not in flags)
    if not missing:
        return None
    opts = ", ".join("--" + o.replace("_", "-") for o in missing)
    reason = f"sdfrd has no {opts} option (not in `sdfrd --help`)"
    if "addressing" in missing:
        reason += (
            "; addressing = auto (what makes a collision step collide) needs sdfrd's address "
            "self-configuration, which this sdfrd does not have yet"
        )
    return reason


def _say(line: str) -> None:
    print(line, flush=True)


def run(
    scenario: Scenario,
    *,
    lab_name: str | None = None,
    run_dir: Path | None = None,
    runs: Path = Path("runs"),
    quick: bool = False,
    capture: str | None = None,
    report: bool = True,
    plots: bool = True,
    say: Callable[[str], None] = _say,
    backend: Backend | None = None,
    runtime: str | None = None,
    image: str = DEFAULT_IMAGE,
    medium: str | None = None,
) -> RunResult:
    """Run `scenario` on a new lab (always taken down); progress goes to `say`.

    The run folder is `run_dir`, or a new ``runs/<name>-<time>``.  `quick` uses the steps'
    `quick` durations; `capture`, `runtime` and `medium` override the scenario's; `image` is
    the robot image of the docker runtime; without `plots` the report has no PNGs.  Skipped
    (status "skipped", with the reason said) when sdfrd lacks an option the scenario needs.
    """
    if backend is None and scenario.hosts:
        from netlab.spanlab import scenario_backend

        backend = scenario_backend(scenario)
    backend = backend or Backend()
    if capture is not None:
        scenario = replace(scenario, capture=capture)
    if runtime is not None:
        scenario = replace(scenario, runtime=runtime)
    if medium is not None:
        scenario = replace(scenario, medium=medium)
    if not backend.can_capture:
        scenario = replace(scenario, capture="none")
    head = (
        f"scenario {scenario.name}: {len(scenario.names)} robots"
        f"{' (containers)' if scenario.runtime == 'docker' else ''}"
        f"{' on radios' if scenario.medium == 'radio' else ''}, beacon {scenario.beacon:g} s"
        f"{' (the product default is 10 s)' if scenario.beacon != PRODUCT_BEACON else ''}"
    )
    spec = LabSpec(
        lab_name or default_lab_name(),
        scenario.seed,
        scenario.fleet,
        UnitDisc(scenario.radius),
        scenario.addressing,
        scenario.runtime,
        image,
        scenario.medium,
        scenario.air_medium,
    )
    reason = missing_requirements(scenario, backend.flags(spec))
    if reason is not None:
        say(f"{head}\n  SKIPPED: {reason}")
        return RunResult(
            scenario.name,
            "skipped",
            reason=reason,
            robots=len(scenario.names),
            beacon=scenario.beacon,
        )
    folder = Path(run_dir).absolute() if run_dir is not None else new_run_dir(runs, scenario.name)
    folder.mkdir(parents=True, exist_ok=True)
    say(f"{head}{', quick' if quick else ''}; run folder {folder}")
    engine = Run(scenario, backend, folder, spec, quick, say)
    return engine.execute(report=report, plots=plots)
