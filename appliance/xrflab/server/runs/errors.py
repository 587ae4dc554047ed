"""The run supervisor's error: a request about runs it cannot honour (not now, no such build, a
build that failed). Its own module, below the run data (run.py) and the build catalog (catalog.py)
that both raise it: when it lived in run.py, catalog and run imported each other."""

from __future__ import annotations

from ...errors import XrfError


class SupervisorError(XrfError):
    """A request the supervisor cannot honour (by default: not now, 409)."""

    status = 409
