"""What a step's action and a check's judge are given: a small context, not the engine.

* `Fleet`: whose daemon runs (in start order) and what this run published on each robot;
  every change of who runs is written to the truth log with the medium's links.
* `History`: what the run has done so far, written by the engine as it walks the steps:
  each step's wall-clock window, /proc readings around the steps a resources check
  measures, the start of the last action step, the checks left for the captures.
* `StepContext`: what an action uses (the lab, the clock, the fleet, the probe, the truth,
  progress lines); `CheckContext`: what a judge uses (the same, the observer's samples, the
  history, whether the run captures).

The engine makes them (`netlab.scenario.engine`); actions and judges import only this.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from netlab import procstat
from netlab.clock import Clock
from netlab.observe import Observer, Probe
from netlab.samples import Sample, indicators_before
from netlab.scenario.backend import LabLike
from netlab.scenario.conditions import Updates
from netlab.scenario.model import Scenario, reference
from netlab.scenario.results import CheckResult
from netlab.scenario.spec import Robots, Selectors, Span, StepError, seconds, select_groups
from netlab.scenario.steps import Start, Step
from netlab.truth import TruthLog, TruthState

#: Robot -> its reading, at the start and at the end of a step.
Readings = tuple[dict[str, procstat.Usage], dict[str, procstat.Usage]]


class Fleet:
    """The scenario's robots as the steps change them: who runs, what this run published."""

    def __init__(self, selectors: Selectors, lab: LabLike, truth: TruthLog) -> None:
        self._selectors = selectors
        self._lab = lab
        self._truth = truth
        self._running: list[str] = []
        #: Robot -> service name -> the id this run published it under.
        self.services: dict[str, dict[str, str]] = {n: {} for n in selectors.names}

    @property
    def running(self) -> tuple[str, ...]:
        """The robots whose daemon runs, in start order."""
        return tuple(self._running)

    def runs(self, name: str) -> bool:
        return name in self._running

    def names(self, sel: Robots) -> tuple[str, ...]:
        """The robots `sel` names ("running": those whose daemon runs)."""
        return self._selectors.robots(sel, self._running)

    def groups(self, groups: Sequence[Robots]) -> list[tuple[str, ...]]:
        return select_groups(self._selectors, groups)

    def running_of(self, sel: Robots | None) -> list[str]:
        """The robots `sel` names whose daemon runs (None: every running robot)."""
        if sel is None:
            return list(self._running)
        return [r for r in self.names(sel) if r in self._running]

    def need_running(self, name: str, what: str) -> None:
        if name not in self._running:
            raise StepError(f"cannot {what} on {name}: its sdfrd is not running")

    def started(self, names: Iterable[str]) -> None:
        self._running += [n for n in names if n not in self._running]
        self.record_truth()

    def gone(self, name: str) -> None:
        if name in self._running:
            self._running.remove(name)
        self.record_truth()

    def record_truth(self) -> TruthState:
        # A robot's own link loss can add up to 100 %: no datagram passes, so no link.
        links = [pair for pair, loss in self._lab.links().items() if loss < 100.0]
        return self._truth.record(links, self._running)


@dataclass
class History:
    """What the run has done so far; the engine writes it, the judges read it."""

    steps: Sequence[Step]
    #: Step (1-based) -> its wall-clock start and end.
    windows: dict[int, tuple[float, float]] = field(default_factory=dict)
    #: Step -> /proc readings of the daemons at its start and end (the measured steps only).
    usage: dict[int, Readings] = field(default_factory=dict)
    #: Wall-clock start of the last action step.
    action_wall: float = 0.0
    #: Updates checks counted in the captures at the end: result, condition, window.
    deferred: list[tuple[CheckResult, Updates, float, float]] = field(default_factory=list)
    _baseline: tuple[float, dict[str, dict[str, float]]] | None = field(
        default=None, init=False, repr=False
    )

    def window(self, index: int, ref: str | None) -> tuple[int, tuple[float, float]]:
        """The step that `ref` names looking back from step `index`, and its window."""
        step = reference(self.steps, index, ref)
        return step, self.windows[step]

    def indicators_before_last_step(self, samples: Sequence[Sample]) -> dict[str, dict[str, float]]:
        """Each robot's indicators in the last samples before the last action step began,
        worked out once per step (a polled check asks again and again)."""
        if self._baseline is None or self._baseline[0] != self.action_wall:
            self._baseline = (self.action_wall, indicators_before(samples, self.action_wall))
        return self._baseline[1]


@dataclass(frozen=True)
class Context:
    """What actions and judges share."""

    scenario: Scenario
    lab: LabLike
    clock: Clock
    fleet: Fleet
    probe: Probe
    truth: TruthLog
    #: A progress line (the engine puts the run's time before it).
    say: Callable[[str], None]

    def seconds(self, span: Span) -> float:
        return seconds(span, self.scenario.beacon)


@dataclass(frozen=True)
class StepContext(Context):
    """What an action step is carried out with."""

    #: Whether the steps' `quick` durations apply.
    quick: bool = False

    def duration(self, full: Span, quick: Span | None) -> float:
        """Seconds of a step that lasts `full`, or `quick` in a quick run."""
        return self.seconds(quick if self.quick and quick is not None else full)

    def options(self, step: Start | None = None) -> dict[str, Any]:
        """sdfrd's options for a start: the scenario's beacon and [sdfrd], the step's own."""
        return {
            "beacon_interval": self.scenario.beacon,
            **self.scenario.sdfrd,
            **(step.options if step is not None else {}),
        }

    def text(self, names: Sequence[str]) -> str:
        """The robots for a progress line: "all N" for the whole fleet."""
        if len(names) > 2 and set(names) == set(self.scenario.names):
            return f"all {len(names)}"
        return ", ".join(names)


@dataclass(frozen=True)
class CheckContext(Context):
    """What a check is judged with."""

    observer: Observer
    history: History
    #: Whether tcpdump records the run (the updates check counts in its captures).
    captured: bool
    #: The run's start on the clock's monotonic time.
    t0: float

    def elapsed(self) -> float:
        """Seconds since the run began."""
        return self.clock.monotonic() - self.t0
