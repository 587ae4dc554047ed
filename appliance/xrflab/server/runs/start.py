"""Starting a run: the one service every route that starts one calls (the Bench page's
POST /api/runs, a project build's POST /api/projects/{pid}/builds/{bid}/run from the Projects
page, the editor's "Build & run" and the Bench page's project entries).

Before, the two routes did it differently: the Projects path left out the bench lease's
bookkeeping (the run the holder started) and feature-detected the supervisor's options. Now both
get the same side effects, in this order: the supervisor starts the run (with the timing option),
the lease notes the run its holder started (lease.started_run: its end is the holder's activity),
the audit trail records the start, or the refusal.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from starlette.requests import HTTPConnection

from ..security import audit
from ..security.accounts import User
from ..security.auth import client_address
from .store import RunRow
from .supervisor import Supervisor, SupervisorError


@dataclass(frozen=True)
class RunRequest:
    build: str  # a catalog name: an example, a template, or project-<pid>-build-<bid>
    sim: str | None = None  # the build's plant unless given
    max_cycles: int | None = None  # leave the loop after N cycles
    log_timing: bool = False  # the loop logs every cycle's timing (cycle_timing.xrf)


async def start_run(
    conn: HTTPConnection,
    user: User,
    req: RunRequest,
    owner: str | None = None,
    audit_detail: dict[str, Any] | None = None,
) -> RunRow:
    """Start `req` for `user` (who asked: the lease and the audit name them). `owner`: whose run
    it is (who may see it), `user` unless given (a project's build runs as its owner's, even when
    an educator starts it). `audit_detail`: what the route adds to the audit record. Raises
    SupervisorError (with its HTTP status), recorded in the audit trail as run.start_failed."""
    sup: Supervisor = conn.app.state.supervisor
    detail = audit_detail or {}
    try:
        row = await sup.start_run(
            req.build,
            req.sim,
            req.max_cycles,
            owner=user.username if owner is None else owner,
            log_timing=req.log_timing,
        )
    except SupervisorError as exc:
        audit.record(user, "run.start_failed", {"build": req.build, **detail, "error": str(exc)}, client_address(conn))
        raise
    lease = conn.app.state.security.lease
    if lease is not None:
        lease.started_run(user, row.id)
    audit.record(user, "run.start", {"run": row.id, "build": req.build, "sim": row.sim, **detail}, client_address(conn))
    return row
