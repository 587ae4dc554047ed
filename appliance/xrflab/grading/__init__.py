"""Assignments that check themselves (issue 32): scenarios, the runner, the checks, the results.

    from xrflab.grading import load, grade_project, grade_executable, GradeQueue

docs/educators/grading.md is the educator's guide and the interface the pages build on.
"""

from .queue import GradeQueue, Job
from .results import STATUSES, CheckResult, GradeResult
from .runner import Limits, grade_executable, grade_project, local_launcher
from .scenario import Check, Command, Scenario, ScenarioError, Setpoint, check_signals, load

__all__ = [
    "STATUSES",
    "Check",
    "CheckResult",
    "Command",
    "GradeQueue",
    "GradeResult",
    "Job",
    "Limits",
    "Scenario",
    "ScenarioError",
    "Setpoint",
    "check_signals",
    "grade_executable",
    "grade_project",
    "load",
    "local_launcher",
]
