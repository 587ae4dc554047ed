"""The run's limits guard looks every 4 s, on the idle reader's boundaries (issue 30 item 4:
its cgroup files and statvfs once a second were a tenth of the idle event loop's Python). A
guard, not a bound: the kernel has refused the page, the fork or the write already (a run over
a limit is stopped by the guard: tests/sandbox/test_limits.py). Counted, not timed: the looks
of the guard (`RunLimits.looks`) over a window, in-process, with a real process as the run's
and a run folder of its own (nothing to walk)."""

from __future__ import annotations

import asyncio
import subprocess
from pathlib import Path

from xrflab.server.runs import watch
from xrflab.server.runs.children import Child
from xrflab.server.runs.limits import RunDisk, RunLimits
from xrflab.server.runs.run import Run
from xrflab.server.runs.store import RunStore
from xrflab.server.settings import Settings

WINDOW_S = 6.5  # the point: a window of the guard's time whose looks are counted


def test_the_limits_guard_looks_every_four_seconds(tmp_path: Path) -> None:
    async def main() -> int:
        proc = Child(subprocess.Popen(["sleep", "60"]))
        try:
            run = Run(
                row=RunStore(tmp_path / "runs.db").create("b", "relbot", "", str(tmp_path)),
                proc=proc,
                shm="",
                run_dir=tmp_path,
                build=None,  # type: ignore[arg-type]
            )
            limits = RunLimits(tmp_path, disk=RunDisk(tmp_path, image=tmp_path / "image"))
            assert not limits.walks_disk
            store, hub = None, None  # (told only of a run over a limit)
            guard = asyncio.create_task(watch.limits_guard(run, limits, Settings(), store, hub))  # type: ignore[arg-type]
            await asyncio.sleep(WINDOW_S)  # on purpose: the window whose looks are counted
            assert not guard.done(), guard  # (nothing over: it keeps looking)
            guard.cancel()
            return limits.looks
        finally:
            proc.popen.kill()
            await proc.wait()

    looks = asyncio.run(main())
    # 4 s apart: 1 or 2 in the window (6-7 before: once a second)
    assert 1 <= looks <= 2, f"the limits guard looked {looks} times in {WINDOW_S} s"
