"""Run a shell probe in the run sandbox as a run would (GuestSpawner), print one JSON line:
the launcher's report, the exit code and what the probe saw. Started by test_launcher.py,
possibly as another user: needs only the standard library and xrflab's pure-Python modules.

usage: guest_probe.py APPLIANCE_DIR PROBE_SCRIPT ALLOW_MISSING(0|1) [DATA_DIR RUN_DISK_HELPER]

With DATA_DIR (and the socket of a run-disk helper serving it), the run folder is
DATA_DIR/runs/<pid> (kept) as a run's would be; else a temporary folder (removed).
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path

# Run inside the sandbox by a bare python3 (no pytest, no venv .pth): the checkout's appliance/
# comes on argv.
sys.path.insert(0, sys.argv[1])
from xrflab.server.runs.guest_spawn import GuestSpawner  # noqa: E402
from xrflab.server.settings import Settings  # noqa: E402


async def main() -> None:
    tmp = Path(tempfile.mkdtemp(prefix="xrf-guest-test-"))
    data, helper = (Path(sys.argv[4]), sys.argv[5]) if len(sys.argv) > 5 else (tmp, "/nonexistent")
    run = data / "runs" / str(os.getpid())
    run.mkdir(parents=True)
    spawner = GuestSpawner(
        Settings(
            data_dir=data,
            allow_unconfined=sys.argv[3] == "1",
            real_bench=False,
            run_disk_mb=16,
            run_files=256,
            runs_total_mb=1024,
            run_disk_helper=helper,
        )
    )
    shm = Path("/dev/shm") / f"xrf-guest-test-{os.getpid()}"
    limits = None
    try:
        # As a run: its cgroup and file system first (launch.spawn).
        limits = await spawner.prepare_limits(spawner.cgroup_name(f"probe{os.getpid()}"), run, tmp / "run.img")
        spawner.prepare_dirs(run, shm)
        with open(run / "out.txt", "wb") as out:
            proc, report = await spawner.spawn(
                Path(sys.argv[2]), run, shm, {"PATH": "/usr/bin:/bin"}, [], out, limits=limits
            )
        rc = await proc.wait()
        print(
            json.dumps(
                {
                    "report": report.as_dict(),
                    "error": report.error,
                    "rc": rc,
                    "pid": report.pid,
                    "output": (run / "out.txt").read_text(),
                    "host_uid": os.getuid(),
                    "run_dir": str(run),
                }
            )
        )
    finally:
        if limits is not None:
            await asyncio.to_thread(limits.release)
        shutil.rmtree(shm, ignore_errors=True)
        shutil.rmtree(tmp, ignore_errors=True)


asyncio.run(main())
