"""What grading answers: one `CheckResult` per check, one `GradeResult` per (scenario, build).

Both are plain dataclasses with `as_dict()` (the HTTP API's and `xrf grade --json`'s shape,
docs/educators/grading.md "Results"); the browser pages draw the plot of each check from
`plot` (the signal's samples over the check's window, decimated, and the bound lines).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

# How a run went. Only "completed" grades every check from the log; the others give 0 points to
# the checks whose window the run did not reach, with `reason` saying why.
STATUSES = ("completed", "build_failed", "start_failed", "crashed", "hung", "never_ran", "error")
PLOT_POINTS = 400  # samples per check's plot (decimated: a plot, not the log)


@dataclass
class CheckResult:
    id: str
    kind: str
    points: float  # what it is worth
    earned: float  # points or 0
    passed: bool
    value: float | None = None  # the measured figure (rise time in s, overshoot in %, ...), None if none
    limit: str = ""  # what it was held to, in words ("<= 10 %")
    message: str = ""  # the educator's message (shown when it fails)
    reason: str = ""  # why it failed or could not be evaluated, in words
    line: int = 0  # the scenario line of the check
    plot: dict[str, Any] | None = (
        None  # {"signal", "t": [...], "y": [...], "bounds": [{"y"|"t", "label"}], "window": [t1, t2]}
    )

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class GradeResult:
    scenario: str
    status: str  # one of STATUSES
    reason: str = ""  # "" when completed; otherwise what went wrong, for the student
    earned: float = 0.0
    points: float = 0.0  # the scenario's maximum
    checks: list[CheckResult] = field(default_factory=list)
    build: str = ""  # which build ran (catalog name or executable)
    run: int | None = None  # the appliance's run record (its log and output: /api/logs/runs/{run})
    reached_run_s: float | None = None  # loop time the controller entered RUN
    loop_time_s: float = 0.0  # how far the loop got
    wall_s: float = 0.0  # how long grading took
    virtual_time: bool = False  # ran in simulated time (XRF_VIRTUAL_TIME)
    log: str = ""  # the log file read (path)
    output_tail: list[str] = field(default_factory=list)  # the controller's last printed lines
    alarms: list[str] = field(default_factory=list)  # what went wrong during the run, in words
    missed: int = 0  # deadline misses the loop counted

    def total(self) -> None:
        self.earned = round(sum(c.earned for c in self.checks), 6)
        self.points = round(sum(c.points for c in self.checks), 6)

    def as_dict(self, plots: bool = True) -> dict[str, Any]:
        d = asdict(self)
        if not plots:
            for c in d["checks"]:
                c["plot"] = None
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> GradeResult:
        checks = [CheckResult(**c) for c in d.get("checks", [])]
        return cls(**{**d, "checks": checks})
