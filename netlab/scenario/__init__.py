"""Scenarios: a timeline of steps and checks, run against a real `netlab.lab.Lab`.

In Python (tests)::

    sc = Scenario(
        "split", robots=4, beacon=0.5, groups={"a": ["r1", "r2"], "b": ["r3", "r4"]},
        steps=[
            Start(),
            Publish("all", "camera", "sensor.camera"),
            Wait(Lists(), within="2 s"),
            Partition(["a", "b"], label="split"),
            Check(Lists(groups=["a", "b"]), within="3 beacons"),
            Merge(label="merge"),
            Check(Lists(), within="1 beacon + 1 s"),
        ],
    )
    result = run(sc, runs=Path("runs"))      # RunResult: .ok, .checks, .run_dir

or as a TOML file (`load(path)`, ``netlab run FILE``); the bundled ones are in
``netlab/scenarios/`` (`bundled()`, ``netlab run NAME``) and show the format::

    [scenario]
    name = "split"
    robots = 4            # r1..r4, or a list of names
    beacon = 0.5          # seconds; the product default is 10
    [groups]
    a = ["r1", "r2"]
    [[step]]
    start = "all"
    [[step]]
    check = "lists"       # a condition; `wait` instead of `check` stops the run on failure
    groups = ["a", "b"]
    within = "3 beacons"  # or 1.5, "1.5 s", "500 ms", "1 beacon + 1 s"

Each ``[[step]]`` has one action key, whose value is its main argument; its other keys are
that step's fields (the step classes below name them).  Robots are selected by name, by group
name, ``"all"`` or ``"running"`` (those whose daemon the scenario started and has not stopped),
or a list of these.

Steps run one after the other.  A check polls its condition until it holds, up to a deadline
(`within`) counted from the end of the last action step before it, so consecutive checks of one
event share that event's clock; `during` makes it hold for that long too.  A failed `check` is
recorded and the run goes on; a failed `wait` ends the run (later steps rely on it).  Checks
consider the robots whose daemons run: a stopped robot is listed by nobody and lists nobody.

During a run: tcpdump on every robot and on the medium (``capture``), an `Observer` sampling
the neighbour lists against the medium's truth, progress lines, and at the end ``run.json``
(samples and check results), ``report.json`` and the plots of `netlab.report` in the run folder,
with the pcaps and each daemon's log (``logs/``) kept for inspection.

The package, in the order a run reads it: `spec` (durations, robot selection, the checks on
fields), `steps` and `conditions` (one frozen dataclass each, with its file keys as fields and
the `STEPS`/`CONDITIONS` registries), `model` (`Scenario`), `files` (TOML read through the
dataclasses' own fields), `backend` (what the engine needs of a lab, a daemon and time),
`context` (what an action or a judge is given: `StepContext`, `CheckContext`), `actions` (one
function per step kind), `judges` (one per condition kind), `engine` (`Run`, `run`: the only
module that holds a run; actions and judges never import it), `results` and `runfolder`.  A
new step or check is a class in `steps`/`conditions` (registered there) and its function in
`actions`/`judges`, which takes the context and the step or condition.
"""

from netlab.scenario.backend import Backend, LabLike, LabSpec, sdfrd_flags
from netlab.scenario.conditions import (
    CONDITIONS,
    Agreement,
    Condition,
    DistinctAddresses,
    Flaps,
    Indicator,
    InHistory,
    Lists,
    Medium,
    Resources,
    Unreachable,
    Updates,
)
from netlab.scenario.engine import PRODUCT_BEACON, Run, default_lab_name, missing_requirements, run
from netlab.scenario.files import BUNDLED_DIR, bundled, find, from_dict, load, loads
from netlab.scenario.model import Scenario
from netlab.scenario.results import CheckResult, RunResult
from netlab.scenario.runfolder import RUN_JSON, rebuild_report
from netlab.scenario.spec import Duration, ScenarioError, StepError, seconds
from netlab.scenario.steps import (
    STEPS,
    Check,
    Collision,
    Kill,
    Merge,
    Mobility,
    Move,
    Partition,
    Publish,
    Quality,
    Restart,
    Shape,
    Sleep,
    Start,
    Step,
    Stop,
    Unpublish,
    Wait,
    twin_mac,
)
from netlab.scenario.topology import LAYOUT_STEPS, add_robots, check_layout, lay_out

__all__ = [
    "BUNDLED_DIR",
    "CONDITIONS",
    "LAYOUT_STEPS",
    "PRODUCT_BEACON",
    "RUN_JSON",
    "STEPS",
    "Agreement",
    "Backend",
    "Check",
    "CheckResult",
    "Collision",
    "Condition",
    "DistinctAddresses",
    "Duration",
    "Flaps",
    "InHistory",
    "Indicator",
    "Kill",
    "LabLike",
    "LabSpec",
    "Lists",
    "Medium",
    "Merge",
    "Mobility",
    "Move",
    "Partition",
    "Publish",
    "Quality",
    "Resources",
    "Restart",
    "Run",
    "RunResult",
    "Scenario",
    "ScenarioError",
    "Shape",
    "Sleep",
    "Start",
    "Step",
    "StepError",
    "Stop",
    "Unpublish",
    "Unreachable",
    "Updates",
    "Wait",
    "add_robots",
    "bundled",
    "check_layout",
    "default_lab_name",
    "find",
    "from_dict",
    "lay_out",
    "load",
    "loads",
    "missing_requirements",
    "rebuild_report",
    "run",
    "sdfrd_flags",
    "seconds",
    "twin_mac",
]
