"""The build queue: a project's builds, one at a time, each in its sandbox.

One worker thread takes builds from a FIFO queue, one at a time (the loop's CPU is never
starved by parallel builds). A build runs ``xrflab.build`` on a version of the project's source
in a fresh build folder, inside a sandbox of its own; this module puts the steps of one build
together and records and announces its progress (``build`` messages: queued, building, its log
lines, ok/failed). The steps live in modules of their own:

- ``build_key``: when an earlier build can be reused instead (same source hash and toolchain);
- ``build_user``: who the build runs as and what that user may reach; ``rt_core_mirror``: an
  rt_core install the build user can read;
- ``sandbox_launch``: starting the sandbox and enforcing the wall time; ``sandbox_config``: its
  limits; ``sandbox``: the sandbox process itself; ``build_procs``: ending a build's processes;
- ``build_result``: the build inside the sandbox and the result file it hands back;
- ``build_log``: the build's log file and live lines; ``diagnostics``: its errors and summary.

This module is also the sandbox's command (``python -m xrflab.projects.builder --sandbox CONFIG --
CMD`` and ``--inner SRC BUILD_DIR``, ``main``): what a process listing shows of a build.
"""

from __future__ import annotations

import contextlib
import os
import queue
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from .build_key import source_hash, toolchain_id
from .build_log import BuildLog, Publish
from .build_procs import RunningBuilds
from .build_result import inner_main, read_result
from .build_user import check_reachable, ensure_build_user, share_source
from .diagnostics import parse_diagnostics, summarise
from .rt_core_mirror import rt_core_for_user
from .sandbox import sandbox_main
from .sandbox_config import SandboxConfig, SandboxSpec
from .sandbox_launch import run_sandboxed
from .store import BuildRow, ProjectRow, ProjectStore


@dataclass
class _Job:
    build: BuildRow
    project: ProjectRow
    src: Path


@dataclass
class Builder:
    store: ProjectStore
    projects_root: Path
    publish: Publish
    config: SandboxConfig = field(default_factory=SandboxConfig)
    # Covered in the build's mount namespace except for what the build needs (the data folder).
    hide_dir: Path | None = None

    def __post_init__(self) -> None:
        self._queue: queue.Queue[_Job | None] = queue.Queue()
        self._pending: list[int] = []
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self.current: int | None = None
        self._user: tuple[int, int, str] | None = None
        self._running = RunningBuilds()
        self.on_done: list[Callable[[BuildRow], None]] = []

    # -- public ---------------------------------------------------------------------------------

    def submit(self, project: ProjectRow, src: Path) -> tuple[BuildRow, bool]:
        """Queue a build of the project's current source; (build, reused). An unchanged source
        (same hash, same toolchain) that built before is not built again: that build is returned."""
        digest = source_hash(src)
        tc = self.toolchain_id()
        old = self.store.reusable(project.id, digest, tc)
        if old is not None:
            return old, True
        row = self.store.create_build(project, digest, tc)
        with self._lock:
            self._pending.append(row.id)
            self._start()
        self._queue.put(_Job(row, project, src))
        self._announce(row, "queued", position=self.position(row.id))
        return row, False

    def position(self, build_id: int) -> int:
        with self._lock:
            ids = ([self.current] if self.current else []) + self._pending
        return ids.index(build_id) if build_id in ids else -1

    def toolchain_id(self) -> str:
        return toolchain_id()

    def stop(self, timeout: float = 10.0) -> None:
        """End the worker: queued builds are dropped, running ones killed; waits up to `timeout`
        for it to have written its last record (the store is closed next)."""
        self._queue.put(None)
        self._running.kill_all()  # this builder's builds only: another appliance's go on
        if self._thread is not None:
            self._thread.join(timeout)

    # -- worker ---------------------------------------------------------------------------------

    def _start(self) -> None:
        if self._thread is None or not self._thread.is_alive():
            self._thread = threading.Thread(target=self._work, name="xrf-project-builds", daemon=True)
            self._thread.start()

    def _work(self) -> None:
        while True:
            job = self._queue.get()
            if job is None:
                return
            with self._lock:
                if job.build.id in self._pending:
                    self._pending.remove(job.build.id)
                self.current = job.build.id
            try:
                row = self._build(job)
            except Exception as exc:  # anything unexpected still ends the build visibly
                row = self.store.update_build(
                    job.build.id, status="failed", ended=time.time(), result=f"internal error: {exc!r}"
                )
                self._announce(row, "failed")
            finally:
                with self._lock:
                    self.current = None
            for cb in self.on_done:
                with contextlib.suppress(OSError):
                    cb(row)

    def _announce(self, row: BuildRow, status: str, **extra: Any) -> None:
        self.publish(
            "build",
            {
                "build_id": row.id,
                "project_id": row.project_id,
                "owner": row.owner,
                "status": status,
                "result": row.result,
                **extra,
            },
        )

    def _build(self, job: _Job) -> BuildRow:
        from .. import build

        cfg = self.config
        project_dir = job.src.parent
        build_dir = project_dir / "builds" / str(job.build.id)
        log_path = build_dir.with_suffix(".log")
        build_dir.mkdir(parents=True, exist_ok=False)
        t0 = time.monotonic()
        row = self.store.update_build(job.build.id, status="building", started=time.time(), log_path=str(log_path))
        self._announce(row, "building")
        with open(log_path, "w", encoding="utf-8", errors="replace") as logf:
            log = BuildLog(logf, self.publish, row)
            error = ""
            timed_out = False
            ok = False
            details: dict[str, Any] = {}
            try:
                prefix = build.ensure_rt_core(log)
                uid, gid, note = self._ensure_user()
                log(f"sandbox: {note}")
                cache_dir = rt_core_for_user(self.projects_root, prefix, uid)
                check_reachable(build_dir, uid, gid, self.hide_dir or self.projects_root)
                os.chown(build_dir, uid, gid)
                os.chmod(build_dir, 0o751)  # the build user's; others may only pass (no listing)
                share_source(job.src, uid, gid)
                timed_out, rc = run_sandboxed(
                    job.src,
                    build_dir,
                    cache_dir,
                    uid,
                    gid,
                    log,
                    config=cfg,
                    hide_dir=self.hide_dir,
                    running=self._running,
                )
                result = read_result(build_dir)
                ok = rc == 0 and not timed_out and bool(result.get("ok"))
                if ok:
                    exe = Path(result["executable"]).resolve()
                    if not exe.is_relative_to(build_dir.resolve()) or not exe.is_file():
                        ok, error = False, "the build's executable is not inside its build folder"
                    else:
                        details["executable_name"] = exe.name
                        row = self.store.update_build(row.id, executable=str(exe))
                        details["layout"] = result.get("layout")
                        details["twenty_sim"] = result.get("twenty_sim")
                else:
                    error = result.get("error", "") or (f"the build failed (exit {rc})" if rc else "")
            except (build.BuildError, RuntimeError, OSError) as exc:
                error = str(exc).splitlines()[0]
                log(f"error: {error}")
            duration = time.monotonic() - t0
            diags = parse_diagnostics(log.lines, job.src, build_dir)
            details["diagnostics"] = diags[:200]
            details["sandbox"] = asdict(cfg)
            details.update(self._project_facts(job.src))
            if ok and details.get("twenty_sim"):
                freq = details["twenty_sim"].get("frequency_hz")
                if freq:
                    details["cycle_freq"] = freq
            result_text = summarise(ok, log.lines, diags, cfg, timed_out, error, duration)
            log(("OK: " if ok else "FAILED: ") + result_text)
        row = self.store.update_build(
            row.id,
            status="ok" if ok else "failed",
            ended=time.time(),
            duration=duration,
            result=result_text,
            details=details,
        )
        self._announce(row, row.status, duration=duration)
        return row

    def _project_facts(self, src: Path) -> dict[str, Any]:
        from . import source, twentysim

        located = source.locate(src)
        return {
            "twenty_sim_tokens": twentysim.describe(located.project if located else src),
            "messages": source.message_fields(src, located),
        }

    def _ensure_user(self) -> tuple[int, int, str]:
        if self._user is None:
            self._user = ensure_build_user(self.config.user)
        return self._user


def main(argv: list[str]) -> int:
    if argv and argv[0] == "--sandbox":
        sep = argv.index("--")
        return sandbox_main(SandboxSpec.from_json(argv[1]), argv[sep + 1 :])
    if argv and argv[0] == "--inner":
        return inner_main(argv[1], argv[2])
    print(
        "usage: python -m xrflab.projects.builder --sandbox CONFIG -- CMD... | --inner SRC BUILD_DIR", file=sys.stderr
    )
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
