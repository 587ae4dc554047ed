"""Assignments that check themselves (issue 32): scenarios, the runner, the checks, the results.

    from xrflab.grading import load, grade_project, grade_executable, GradeQueue

docs/educators/grading.md is the educator's guide and the interface the pages build on. The
names are looked up on first use: `xrf grade`'s module is imported by every `xrf` call (to build
the parser), and that must not import NumPy and the runner.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "STATUSES": ".results",
    "CheckResult": ".results",
    "GradeResult": ".results",
    "GradeQueue": ".queue",
    "Job": ".queue",
    "Limits": ".runner",
    "grade_executable": ".runner",
    "grade_project": ".runner",
    "local_launcher": ".runner",
    "Check": ".scenario",
    "Command": ".scenario",
    "Scenario": ".scenario",
    "ScenarioError": ".scenario",
    "Setpoint": ".scenario",
    "check_signals": ".scenario",
    "load": ".scenario",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(_EXPORTS[name], __name__), name)
