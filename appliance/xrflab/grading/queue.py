"""A bounded-parallel queue of grading jobs ("re-run on all latest builds").

Each job is one (scenario, build) graded by a function the caller gives (the runner, wrapped with
whatever it needs: a build, the sandbox's launcher); at most `parallel` run at once, on threads
(each job is mostly waiting on its controller process). A job that raises is recorded as an
`error` result, never lost, and never stops the others; each job's own time limits (runner.Limits)
bound how long it can hold a slot. `progress()` is what a page polls.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

from .results import GradeResult

MAX_PARALLEL = 8


@dataclass
class Job:
    key: str  # who and what, e.g. "<assignment>/<project id>"
    status: str = "queued"  # queued, running, done
    result: GradeResult | None = None
    queued_at: float = field(default_factory=time.time)
    started_at: float = 0.0
    ended_at: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        return {
            "key": self.key,
            "status": self.status,
            "queued_at": self.queued_at,
            "started_at": self.started_at,
            "ended_at": self.ended_at,
            "result": None if self.result is None else self.result.as_dict(plots=False),
        }


class GradeQueue:
    def __init__(self, parallel: int = 2, on_done: Callable[[Job], None] | None = None) -> None:
        if not 1 <= parallel <= MAX_PARALLEL:
            raise ValueError(f"parallel must be 1..{MAX_PARALLEL}")
        self.parallel = parallel
        self._pool = ThreadPoolExecutor(max_workers=parallel, thread_name_prefix="xrf-grade")
        self._lock = threading.Lock()
        self.jobs: dict[str, Job] = {}
        self._futures: dict[str, Future[None]] = {}
        self.on_done = on_done

    def submit(self, key: str, grade: Callable[[], GradeResult]) -> Job:
        """Queue `grade` under `key`; a key already queued or running is not queued twice."""
        with self._lock:
            old = self.jobs.get(key)
            if old is not None and old.status != "done":
                return old
            job = Job(key)
            self.jobs[key] = job
            self._futures[key] = self._pool.submit(self._run, job, grade)
            return job

    def _run(self, job: Job, grade: Callable[[], GradeResult]) -> None:
        job.status, job.started_at = "running", time.time()
        try:
            job.result = grade()
        except Exception as exc:  # a job's failure is its result; the queue goes on
            job.result = GradeResult("", "error", reason=f"grading failed: {type(exc).__name__}: {exc}")
        job.status, job.ended_at = "done", time.time()
        if self.on_done is not None:
            try:
                self.on_done(job)
            except Exception:  # the result is kept in the job either way
                pass

    def progress(self) -> dict[str, Any]:
        with self._lock:
            jobs = list(self.jobs.values())
        counts = {s: sum(1 for j in jobs if j.status == s) for s in ("queued", "running", "done")}
        return {"parallel": self.parallel, "total": len(jobs), **counts}

    def wait(self, timeout: float | None = None) -> bool:
        """Every job submitted so far done (True) or the timeout passed (False)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        for fut in list(self._futures.values()):
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            try:
                fut.result(left)
            except TimeoutError:
                return False
        return True

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)
