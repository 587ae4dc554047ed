"""The grading service the appliance makes (server/app.py): an assignment's scenario, grading a
project's latest build with it (a student's "Check my project", an educator's "Re-run all"), the
results per assignment, the table and its CSV.

Files, in <data>/grading/<assignment>/: `scenario.toml` (checked against the assignment's own
sources when stored) and `results/<project id>.json` (the latest result of each project, with
its plots). A graded run is a run record with its run folder like any other (grading/sandbox.py).
A student's own checks are rate-limited per account (`min_interval_s`).
"""

from __future__ import annotations

import asyncio
import csv
import io
import json
import os
import threading
import time
from pathlib import Path
from typing import Any

from starlette.requests import HTTPConnection

from .. import plants
from ..errors import Busy, Invalid, NotFound
from ..projects import assignments as assignment_ids
from . import project as proj
from .queue import GradeQueue, Job
from .results import GradeResult
from .runner import Limits, grade_executable
from .sandbox import sandbox_launcher
from .scenario import Scenario, check_signals, load

MIN_INTERVAL_S = 20.0  # between two checks one student asks for


class GradingService:
    def __init__(
        self, settings: Any, projects: Any, runs_store: Any, loop: asyncio.AbstractEventLoop, parallel: int = 2
    ) -> None:
        self.settings = settings
        self.projects = projects  # ProjectsService
        self.runs_store = runs_store
        self.loop = loop
        self.root: Path = settings.data_dir / "grading"
        self.root.mkdir(parents=True, exist_ok=True)
        self.queue = GradeQueue(parallel, on_done=self._save)
        self.limits = Limits()
        self.min_interval_s = MIN_INTERVAL_S
        self._asked: dict[str, float] = {}
        self._lock = threading.Lock()

    def close(self) -> None:
        self.queue.close()

    # -- scenarios -----------------------------------------------------------------------------------

    def _folder(self, aid: str) -> Path:
        try:
            return self.root / assignment_ids.check_id(aid)
        except ValueError as exc:
            raise Invalid(str(exc)) from None

    def _assignment_src(self, aid: str) -> Path:
        self._folder(aid)
        if self.projects.assignments.get(aid) is None:
            raise NotFound(f"no assignment {aid!r} on this bench")
        return self.projects.assignments.src(aid)

    def set_scenario(self, aid: str, text: str) -> Scenario:
        """Check `text` against the assignment's sources and keep it; ScenarioError with the line."""
        src = self._assignment_src(aid)
        name = f"{aid}.toml"
        scenario = load(text, name, tuple(plants.names()))
        check_signals(scenario, proj.ros2xeno_fields(src), proj.logged_variables(src), name)
        folder = self._folder(aid)
        folder.mkdir(exist_ok=True)
        _write(folder / "scenario.toml", text.encode())
        return scenario

    def scenario(self, aid: str) -> Scenario:
        path = self._folder(aid) / "scenario.toml"
        try:
            text = path.read_text()
        except OSError:
            raise NotFound(f"assignment {aid!r} has no scenario") from None
        return load(text, f"{aid}.toml")

    @staticmethod
    def summary(s: Scenario) -> dict[str, Any]:
        return {
            "text": s.source,
            "name": s.name,
            "robot": s.robot,
            "duration": s.duration,
            "points": s.max_points,
            "checks": [
                {"id": c.id, "kind": c.kind, "points": c.points, "signal": c.signal, "message": c.message}
                for c in s.checks
            ],
        }

    # -- grading -------------------------------------------------------------------------------------

    @staticmethod
    def assignment_of(project: Any) -> str:
        origin = str(project.origin or "")
        if not origin.startswith(assignment_ids.ORIGIN_PREFIX):
            raise NotFound(f"project {project.id} was not made from an assignment: nothing to grade it with")
        return origin[len(assignment_ids.ORIGIN_PREFIX) :]

    def latest_build(self, project: Any) -> Any:
        for b in self.projects.store.builds(project.id, limit=20):
            if b.status == "ok" and b.executable and os.path.isfile(b.executable):
                return b
        return None

    def check_rate(self, username: str) -> None:
        with self._lock:
            now = time.monotonic()
            last = self._asked.get(username)
            if last is not None and now - last < self.min_interval_s:
                wait = int(self.min_interval_s - (now - last)) + 1
                raise Busy(f"checked {now - last:.0f} s ago; again in {wait} s", headers={"Retry-After": str(wait)})
            self._asked[username] = now

    def grade(self, project: Any) -> Job:
        """Queue `project`'s latest runnable build with its assignment's scenario."""
        aid = self.assignment_of(project)
        scenario = self.scenario(aid)
        key = f"{aid}/{project.id}"
        b = self.latest_build(project)
        if b is None:
            return self.queue.submit(key, lambda: self._no_build(scenario, project))
        build = f"project-{project.id}-build-{b.id}"
        exe = Path(b.executable)
        launcher = sandbox_launcher(self.settings, self.runs_store, self.loop, project.owner, build, scenario.robot)
        return self.queue.submit(
            key,
            # simulated time: a graded run is always on the simulated plant (issue 32: seconds, not
            # the scenario's duration); rt_core refuses it on a real board
            lambda: grade_executable(
                scenario, exe, self.settings.runs_dir, launcher, self.limits, virtual_time=True, build=build
            ),
        )

    @staticmethod
    def _no_build(scenario: Scenario, project: Any) -> GradeResult:
        import numpy as np

        from .checks import RunData, evaluate

        r = GradeResult(scenario.name, "build_failed", reason=f"project {project.id} has no successful build to run")
        r.checks = evaluate(scenario, RunData(columns={"t": np.empty(0)}, complete=False, reason="no successful build"))
        r.total()
        return r

    def _save(self, job: Job) -> None:
        aid, _, pid = job.key.partition("/")
        if job.result is None:
            return
        folder = self._folder(aid) / "results"
        folder.mkdir(parents=True, exist_ok=True)
        data = {**job.result.as_dict(), "graded_at": time.time(), "project": int(pid)}
        _write(folder / f"{int(pid)}.json", json.dumps(data).encode())

    def result(self, project: Any) -> dict[str, Any]:
        """The latest job and result; a project not made from an assignment has none (not an error:
        the page asks for every project it shows)."""
        if not str(project.origin or "").startswith(assignment_ids.ORIGIN_PREFIX):
            return {"job": None, "result": None}
        aid = self.assignment_of(project)
        job = self.queue.jobs.get(f"{aid}/{project.id}")
        return {"job": None if job is None else job.as_dict(), "result": self._stored(aid, project.id)}

    def _stored(self, aid: str, pid: int) -> dict[str, Any] | None:
        try:
            return json.loads((self._folder(aid) / "results" / f"{int(pid)}.json").read_text())
        except (OSError, ValueError):
            return None

    # -- the educator's table ------------------------------------------------------------------------

    def projects_of(self, aid: str) -> list[Any]:
        self._assignment_src(aid)
        return self.projects.store.projects_with_origin(assignment_ids.origin(aid))

    def rerun_all(self, aid: str) -> dict[str, Any]:
        self.scenario(aid)
        for p in self.projects_of(aid):
            self.grade(p)
        return self.progress(aid)

    def progress(self, aid: str) -> dict[str, Any]:
        jobs = [j for k, j in list(self.queue.jobs.items()) if k.startswith(f"{aid}/")]
        counts = {s: sum(1 for j in jobs if j.status == s) for s in ("queued", "running", "done")}
        return {"parallel": self.queue.parallel, "total": len(jobs), **counts}

    def table(self, aid: str) -> dict[str, Any]:
        scenario = self.scenario(aid)
        rows = []
        for p in self.projects_of(aid):
            stored = self._stored(aid, p.id)
            job = self.queue.jobs.get(f"{aid}/{p.id}")
            row: dict[str, Any] = {
                "project": p.id,
                "owner": p.owner,
                "name": p.name,
                "job": None if job is None else job.status,
                "build": "",
                "status": "not graded",
                "reason": "",
                "earned": 0.0,
                "points": scenario.max_points,
                "graded_at": None,
                "run": None,
                "checks": {},
            }
            if stored:
                row.update(
                    {k: stored.get(k) for k in ("build", "status", "reason", "earned", "points", "graded_at", "run")}
                )
                row["checks"] = {
                    c["id"]: {"earned": c["earned"], "passed": c["passed"], "value": c["value"]}
                    for c in stored.get("checks", [])
                }
            rows.append(row)
        checks = [{"id": c.id, "kind": c.kind, "points": c.points} for c in scenario.checks]
        return {"assignment": aid, "checks": checks, "rows": rows, "progress": self.progress(aid)}

    def csv(self, aid: str) -> str:
        return grades_csv(self.table(aid))


def _write(path: Path, data: bytes) -> None:
    """Whole or not at all (a reader never sees half a result), readable by the appliance only."""
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


def csv_cell(text: str) -> str:
    """A spreadsheet does not run what a cell says: a cell starting with = + - @, a tab or a carriage
    return is a formula to Excel/LibreOffice (OWASP's list), so it gets a leading quote."""
    return "'" + text if text[:1] in ("=", "+", "-", "@", "\t", "\r") else text


def grades_csv(table: dict[str, Any], extra: tuple[str, ...] = ()) -> str:
    """One grades table as CSV, for this appliance's table and the room's (``extra`` columns such as
    ``bench`` follow the owner). Every text cell passes csv_cell: project names are a student's
    upload names and a room's rows are a bench's own message, so none of it is trusted."""
    out = io.StringIO()
    w = csv.writer(out)
    ids = [str(c["id"]) for c in table["checks"]]
    w.writerow(["owner", *extra, "project", "status", *ids, "total", "max", "build", "graded_at"])

    def text(value: Any) -> str:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return str(value)  # a number is no formula, and -0.5 points stays a number
        return csv_cell("" if value is None else str(value))

    for r in table["rows"]:
        w.writerow(
            [
                text(r["owner"]),
                *[text(r.get(k)) for k in extra],
                text(r["project"]),
                text(r["status"]),
                *[text(r["checks"].get(i, {}).get("earned", "")) for i in ids],
                text(r["earned"]),
                text(r["points"]),
                text(r["build"]),
                text(r["graded_at"]),
            ]
        )
    return out.getvalue()


def grading_of(conn: HTTPConnection) -> GradingService:
    """FastAPI dependency: the app's grading service (made in server/app.py's lifespan)."""
    svc: GradingService = conn.app.state.grading
    return svc
