"""What a run tells: each check's result, and the run's."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


@dataclass
class CheckResult:
    """How one check went: ok True/False, or None when it could not be judged (skipped)."""

    step: int
    kind: str
    description: str
    fatal: bool
    ok: bool | None = None
    took: float | None = None  # seconds from the event to the condition holding
    deadline: float | None = None  # seconds
    during: float | None = None
    at: float = 0.0  # seconds since the run's timeline began
    detail: str = ""
    data: dict[str, Any] = field(default_factory=dict)

    @property
    def result(self) -> str:
        return {True: "ok", False: "FAILED", None: "skipped"}[self.ok]

    def to_json(self) -> dict[str, object]:
        return {
            "step": self.step,
            "kind": self.kind,
            "description": self.description,
            "fatal": self.fatal,
            "ok": self.ok,
            "result": self.result,
            "took_s": self.took,
            "deadline_s": self.deadline,
            "during_s": self.during,
            "at_s": self.at,
            "detail": self.detail,
            **({"data": self.data} if self.data else {}),
        }


@dataclass
class RunResult:
    """How a scenario run went: status "passed", "failed", "error" or "skipped"."""

    scenario: str
    status: str
    run_dir: Path | None = None
    checks: list[CheckResult] = field(default_factory=list)
    error: str | None = None
    reason: str | None = None  # why it was skipped
    robots: int = 0
    beacon: float = 0.0
    duration: float = 0.0
    report: dict[str, Any] | None = None

    @property
    def ok(self) -> bool:
        return self.status == "passed"

    @property
    def failed(self) -> list[CheckResult]:
        return [c for c in self.checks if c.ok is False]

    def to_json(self) -> dict[str, object]:
        return {
            "scenario": self.scenario,
            "status": self.status,
            "run_dir": str(self.run_dir) if self.run_dir else None,
            "error": self.error,
            "reason": self.reason,
            "robots": self.robots,
            "beacon_interval_s": self.beacon,
            "duration_s": self.duration,
            "checks": [c.to_json() for c in self.checks],
        }

    def summary(self) -> list[str]:
        """The checks as a table, and a closing line."""
        lines = [f"{'step':>4}  {'check':54} {'deadline':>9} {'took':>8}  result"]
        for c in self.checks:
            deadline = f"{c.deadline:.2f} s" if c.deadline is not None else "-"
            if c.during is not None:
                deadline = f"for {c.during:.2f} s" if c.deadline is None else f"{deadline}+"
            took = f"{c.took:.2f} s" if c.took is not None else "-"
            desc = c.description if len(c.description) <= 54 else c.description[:51] + "..."
            lines.append(f"{c.step:>4}  {desc:54} {deadline:>9} {took:>8}  {c.result}")
            if c.ok is not True and c.detail:
                lines.append(f"{'':6}{c.detail}")
        ok = sum(c.ok is True for c in self.checks)
        tail = f"{self.scenario}: {self.status.upper()}, {ok} of {len(self.checks)} checks ok"
        lines.append(f"{tail}, in {self.duration:.1f} s")
        if self.error:
            lines.append(f"error: {self.error}")
        return lines
