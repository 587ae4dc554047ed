"""The appliance's launcher for graded runs: the run sandbox every controller runs in
(server/runs/launch.py's `spawn`: own uid, namespaces, cgroup, the run folder as a file system of
its own, a sealed segment), without the bench: no supervisor slot, no lease, no browsers. A
graded run is a run record of its own (status, end, run folder in <data>/runs/<id>), so its log
and output are where every run's are, behind the same routes and ownership rule.

`spawn` is async and makes its child on the appliance's event loop; a grading job runs on a
queue thread, so it hands the coroutine to the loop and waits for it.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import signal
import time
from collections.abc import Coroutine
from pathlib import Path
from typing import Any, TypeVar

from ..server.runs import launch
from ..server.runs.catalog import BuildEntry
from ..server.runs.children import Child
from ..server.runs.guest_spawn import GuestSpawner
from ..server.runs.run import Run, remove_shm
from ..server.runs.store import RunStore
from ..server.settings import Settings
from .runner import Launcher, Started

T = TypeVar("T")
KILL_GRACE_S = 1.0
# The loop options a graded run adds to the appliance's (guest.ENV_ALLOWED has each).
GRADED_KEYS = ("XRF_SIM_FAULTS", "XRF_PRIO", "XRF_QUIET", "XRF_VIRTUAL_TIME", "XRF_HOST_TIMEOUT_ACTION")


class _Sandboxed:
    def __init__(self, proc: Child) -> None:
        self.proc = proc
        self.pid = proc.pid

    def poll(self) -> int | None:
        return self.proc.popen.poll()

    def kill(self) -> None:
        # The launcher passes signals on to the controller; SIGKILL cannot be, so TERM first.
        for sig in (signal.SIGTERM, signal.SIGKILL):
            with contextlib.suppress(ProcessLookupError):
                self.proc.send_signal(sig)
            if self.wait(KILL_GRACE_S) is not None:
                return

    def wait(self, timeout: float) -> int | None:
        deadline = time.monotonic() + timeout
        while self.proc.popen.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)  # polling the launcher's exit: its watcher belongs to the event loop
        return self.proc.popen.returncode


def sandbox_launcher(
    settings: Settings, store: RunStore, loop: asyncio.AbstractEventLoop, owner: str, build: str, plant: str
) -> Launcher:
    """A Launcher for one graded run of `build` (a catalog-style name) owned by `owner`."""
    guests = GuestSpawner(settings)

    def call(coro: Coroutine[Any, Any, T]) -> T:
        return asyncio.run_coroutine_threadsafe(coro, loop).result()

    def launch_one(exe: Path, env: dict[str, str], run_dir: Path) -> Started:
        extra = {k: v for k, v in env.items() if k in GRADED_KEYS}
        graded = dataclasses.replace(
            settings,
            # The loop writes its own log file (the appliance's host writer belongs to the bench's run).
            loop_env={**settings.loop_env, **extra, "XRF_LOG_WRITER": "process"},
        )
        row = store.create(build, plant, "", "")
        store.update(row.id, owner=owner)
        entry = BuildEntry(name=build, kind="graded", path=exe.parent, sim=plant, status="ready", executable=exe)
        try:
            run: Run = call(launch.spawn(row, entry, plant, None, False, graded, guests, store))
        except Exception as exc:
            raise RuntimeError(str(exc)) from exc

        def release() -> None:
            code = run.proc.popen.returncode
            if run.limits is not None:
                call(asyncio.to_thread(run.limits.release))
            remove_shm(run.shm)
            status = "ended" if code == 0 else "crashed"
            store.update(row.id, status=status, ended=time.time(), end_reason="quit" if code == 0 else "crash")

        # The runner closes the segment's descriptor; the Run holds the same one.
        return Started(_Sandboxed(run.proc), run.shm_fd, run.shm, release, run.run_dir, row.id)

    return launch_one
