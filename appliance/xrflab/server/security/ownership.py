"""The one ownership rule, for every route and every WebSocket topic.

A student or observer sees only their own projects, builds, runs, logs, recordings and live
streams; educators see everything (``auth.owns`` is the comparison itself). Someone else's
resource answers exactly like a missing one, the same 404 with the same body, so ids cannot be
probed; every list is filtered by the same rule.

The bench's live run is watched by everyone with WATCH, but not all of it (``scope()``; the hub
calls it for every message it fans out, the snapshot of a new client included):

- everyone: state and allowed commands, alarms, timing, and the robot's motion (encoders, PWM,
  digital I/O in the telemetry): what the room sees anyway;
- the run's owner and educators only: the monitor console (the controller's printed output),
  Ros2Xeno/Xeno2Ros field names and values (telemetry ``xeno2ros``, the setpoint controls), the
  build and program name, the owner and the run folder, and a project's build output.

docs/developers/security.md ("Ownership and what others may watch") is the prose of this.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable
from typing import Any, TypeVar

from starlette.requests import HTTPConnection

from ...errors import NotFound
from ..runs.errors import SupervisorError
from ..ws.hub import Scoped
from .auth import User, owns

T = TypeVar("T")

# How the projects routes name an uploaded project's build in the supervisor's catalog.
PROJECT_BUILD = re.compile(r"project-(\d+)-build-(\d+)")


def user_of(conn: HTTPConnection) -> User | None:
    return conn.app.state.security.resolve(conn)[0]


def may_see(user: User | None, owner: int | str | None) -> bool:
    """The rule: educators see everything, everyone else only their own (no user: nothing)."""
    return user is not None and owns(user, owner)


def not_found(what: str, ident: Any) -> NotFound:
    """The answer for a missing resource and for someone else's: one body for both."""
    return NotFound(f"no {what} {ident}")


def require(
    user: User | None, row: T | None, owner: Callable[[T], Any], what: str, ident: Any, detail: str | None = None
) -> T:
    """`row` if it exists and `user` may see it; else the missing-resource 404 (`detail`: the
    route's own words for a missing one, when it has them)."""
    if row is None or not may_see(user, owner(row)):
        raise NotFound(detail) if detail is not None else not_found(what, ident)
    return row


def _owner_column(row: Any) -> Any:
    return row.owner


def visible(user: User | None, rows: Iterable[T], owner: Callable[[T], Any] = _owner_column) -> list[T]:
    """The rows of a list that `user` may see."""
    return [r for r in rows if may_see(user, owner(r))]


# ---- runs -----------------------------------------------------------------------------------


def run_or_404(conn: HTTPConnection, run_id: int) -> Any:
    """The run record (runs.RunRow) if it exists and is the requester's (or they educate)."""
    return require(user_of(conn), conn.app.state.supervisor.store.get(run_id), lambda r: r.owner, "run", run_id)


def runs(conn: HTTPConnection, limit: int) -> list[Any]:
    """The newest `limit` runs the requester may see, filtered in SQL (an educator: all)."""
    user = user_of(conn)
    if user is None:
        return []
    store = conn.app.state.supervisor.store
    return store.list(limit) if user.is_educator else store.list(limit, owner=user.username)


# ---- starting a run -------------------------------------------------------------------------


def missing_build(conn: HTTPConnection, name: str) -> NotFound:
    """Word for word what the catalog answers for a name it does not know (BuildCatalog.get)."""
    have = ", ".join(e.name for e in conn.app.state.supervisor.catalog.entries())
    return NotFound(f"no build named {name!r}; have: {have}")


async def check_startable(conn: HTTPConnection, name: str) -> None:
    """A run starts from a bundled example/template, or from a build of one's own project;
    anything else is refused as a missing build (404). Educators may run any build.

    The catalog (supervisor.BuildCatalog) also knows uploaded builds by name once their owner ran
    one (routes_projects.run_build registers it), so the name alone must not be enough."""
    user = user_of(conn)
    if user is None:
        raise missing_build(conn, name)
    if user.is_educator:
        return
    m = PROJECT_BUILD.fullmatch(name)
    if m is not None:
        store = conn.app.state.projects.store  # the projects service (made in server/app.py's lifespan)
        project = store.project(int(m.group(1)))
        build = store.build(int(m.group(2)))
        if project is None or build is None or build.project_id != project.id or not may_see(user, project.owner):
            raise missing_build(conn, name)
        return
    catalog = conn.app.state.supervisor.catalog
    if name not in {e.name for e in catalog.entries()}:  # not bundled: an uploaded build by another name
        try:
            entry = catalog.get(name)
        except SupervisorError:  # unknown: start_run answers its own 404
            return
        if entry.kind not in ("example", "template"):
            raise missing_build(conn, name)


# ---- what a WebSocket client sees of the live run -------------------------------------------

# Telemetry everyone may see: the robot's motion and the loop's clock, in each sample (its
# xeno2ros, the controller's own outputs named by the student, is the owner's: {} for the rest),
# and the message's run and loss count (its ros2xeno, the owner's: {}).
PUBLIC_TELEMETRY = frozenset({"run_id", "lost"})
PUBLIC_TELEMETRY_SAMPLE = frozenset({"cycle", "t_ns", "t", "state", "enc", "din", "pwm", "dout", "ros2xeno_t_sent_ns"})


def public_telemetry(payload: dict[str, Any]) -> dict[str, Any]:
    """What someone who may not see a run's owner's part receives of its telemetry message: the
    same fields in the same order, the owner's emptied."""
    out: dict[str, Any] = {}
    for k, v in payload.items():
        if k == "samples":
            out[k] = [
                {
                    sk: (sv if sk in PUBLIC_TELEMETRY_SAMPLE else {})
                    for sk, sv in sample.items()
                    if sk in PUBLIC_TELEMETRY_SAMPLE or sk == "xeno2ros"
                }
                for sample in v
            ]
        elif k == "ros2xeno":
            out[k] = {}
        elif k in PUBLIC_TELEMETRY:
            out[k] = v
    return out


# Run record fields everyone may see; the rest (build, program, owner, run_dir, shm, pid,
# message) are blanked, not removed, so clients read one shape.
PUBLIC_RUN = frozenset(
    {
        "id",
        "sim",
        "started",
        "ended",
        "status",
        "crashed",
        "crash_reason",
        "exit_code",
        "exit_signal",
        "state",
        "cycles",
        "misses",
        "cycle_freq",
        "log_records",
        "log_lost",
        "log_note",
    }
)
# confinement: which protection layers of the run sandbox hold is the bench's, for everyone in
# the room (the dashboard's "runs WITHOUT" banner); it names layers, nothing of the student's.
PUBLIC_RUN_MESSAGE = frozenset({"event", "active", "cycle_freq", "backend", "transport", "channels", "confinement"})


def public_run_row(row: dict[str, Any]) -> dict[str, Any]:
    return {k: (v if k in PUBLIC_RUN else ("" if isinstance(v, str) else None)) for k, v in row.items()}


def scope(topic: str, payload: dict[str, Any], owner_of_run: Callable[[Any], str | None]) -> Scoped | None:
    """Whose a published message is and what everyone else receives instead (None: nothing).
    None as the result: the message is the bench's, for everyone who subscribed."""
    if topic == "telemetry":
        # The public copy is made only if a client that may not see the owner's part takes it
        # (Hub._fan_out): 5 messages a second, most often watched by their owner or an educator.
        return Scoped(
            owner_of_run(payload.get("run_id")),
            lambda: public_telemetry(payload),
        )
    if topic == "monitor":
        return Scoped(owner_of_run(payload.get("run_id")), None)
    if topic == "run":
        row = payload.get("run")
        if not row:
            return None  # "no run yet": nobody's
        public = {k: v for k, v in payload.items() if k in PUBLIC_RUN_MESSAGE}
        public["run"] = public_run_row(row)
        public["redacted"] = True
        if "ros2xeno" in payload:  # the dashboard then clears the previous run's controls and plots
            public.update(program="", ros2xeno=[], xeno2ros=[], setpoint={})
        return Scoped(row.get("owner"), public)
    if topic == "build" and "owner" in payload:  # an uploaded project's build (bundled: no owner)
        return Scoped(payload["owner"], None)
    return None


def attach(hub: Any, supervisor: Any) -> None:
    """Make the hub's fan-out follow the rule (called once the hub and supervisor exist)."""

    def owner_of_run(run_id: Any) -> str | None:
        run = supervisor.current
        if run is not None and run.row.id == run_id:
            return run.row.owner
        if not isinstance(run_id, int) or isinstance(run_id, bool):
            return None  # unknown: nobody's, so only educators see it
        row = supervisor.store.get(run_id)
        return row.owner if row is not None else None

    hub.scope = lambda topic, payload: scope(topic, payload, owner_of_run)
    hub.may_see = may_see


def current_run_is_visible(conn: HTTPConnection, run_id: Any) -> bool:
    """For GET routes showing the live run: may the requester see the owner's part of it?"""
    sup = conn.app.state.supervisor
    run = sup.current
    owner = run.row.owner if run is not None and run.row.id == run_id else None
    if owner is None and isinstance(run_id, int):
        row = sup.store.get(run_id)
        owner = row.owner if row is not None else None
    return may_see(user_of(conn), owner)
