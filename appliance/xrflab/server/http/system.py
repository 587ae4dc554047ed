"""HTTP routes of the System page (issue 10): the ``xrf doctor`` checks and facts about the
appliance (version, data folder, disk, uptime, how the bench is reached). Anyone who may watch.

The doctor runs in a worker thread (it reads /proc and /sys and runs a few commands). It talks
to the FPGA (an INIT-only run of xrf-selfcheck, nothing moves) only when the SPI device is usable
and neither a loop run nor a self-check holds the bench.
"""

from __future__ import annotations

import asyncio
import os
import platform
import shutil
import socket
import time
from pathlib import Path
from typing import Any

from fastapi import APIRouter, Request
from pydantic import BaseModel, Field

from ... import doctor
from ..security.auth import Perm, optional_user, requires

router = APIRouter(prefix="/api/system", tags=["system"])

STARTED = time.time()
_doctor_lock = asyncio.Lock()


class DoctorItem(BaseModel):
    name: str
    status: str = Field(description="ok | missing")
    detail: str = Field(description="why it is missing")


class DoctorCheck(BaseModel):
    id: str
    title: str
    status: str = Field(description="ok | warning | failure | not checked")
    detail: str
    fix: str = Field(description="what to do, when not ok")
    items: list[DoctorItem] = Field(
        default_factory=list, description="parts of the check: the run sandbox's protection layers"
    )


class DoctorResult(BaseModel):
    checked_at: float = Field(description="Unix time")
    duration_s: float
    live: bool = Field(description="the FPGA INIT probe was allowed")
    counts: dict[str, int]
    checks: list[DoctorCheck]


def _host_uptime() -> float | None:
    try:
        return float(Path("/proc/uptime").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None


def _bench_free(request: Request) -> bool:
    sup = request.app.state.supervisor
    run = sup.current
    if run is not None and not run.ended.is_set():
        return False
    sc = getattr(request.app.state, "selfcheck", None)
    return not (sc is not None and sc.current is not None)


@router.get("", dependencies=[requires(Perm.WATCH)])
async def system_info(request: Request) -> dict[str, Any]:
    """Version, data folder and its free disk, uptimes, and the bench's backend and transport."""
    settings = request.app.state.settings
    sup = request.app.state.supervisor
    data_dir = Path(settings.data_dir)
    probe = data_dir
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    try:
        usage = shutil.disk_usage(probe)
        disk = {"total": usage.total, "used": usage.used, "free": usage.free}
    except OSError:
        disk = None
    bench = dict(sup.bench())
    real = bench.get("mode") == "real"
    bench["transport"] = "spidev" if real else "sim"
    bench["spi_device"] = settings.spi_device if real else ""
    bench["backend"] = "evl" if bench.get("evl") else "posix"
    run = sup.current
    if run is not None and not run.ended.is_set() and run.channels is not None:
        info = run.channels.info  # what the running loop really uses
        bench["backend"] = info.get("backend", bench["backend"])
        bench["transport"] = info.get("transport", bench["transport"])
    return {
        "version": request.app.version,
        "hostname": socket.gethostname(),
        "platform": f"{platform.system()} {platform.release()} ({platform.machine()})",
        "python": platform.python_version(),
        "pid": os.getpid(),
        "data_dir": str(data_dir),
        "disk": disk,
        "started": STARTED,
        "uptime_s": round(time.time() - STARTED, 1),
        "host_uptime_s": _host_uptime(),
        "bench": bench,
        "run_active": bool(run is not None and not run.ended.is_set()),
    }


@router.get("/doctor", response_model=DoctorResult, dependencies=[requires(Perm.WATCH)])
async def system_doctor(request: Request) -> dict[str, Any]:
    """Run every `xrf doctor` check now (the page's Refresh)."""
    settings = request.app.state.settings
    # Talking to the FPGA (INIT) is an educator's call; everyone else sees the passive checks.
    user = optional_user(request)
    live = _bench_free(request) and user is not None and user.is_educator
    async with _doctor_lock:  # one at a time; a second caller waits for a fresh result
        t0 = time.monotonic()
        # The confinement check starts /bin/true in the run sandbox exactly as a run would, with
        # this appliance's settings (its user, --allow-unconfined).
        results = await asyncio.to_thread(
            doctor.run_checks,
            Path("/"),
            data_dir=str(settings.data_dir),
            spi_device=settings.spi_device,
            live=live,
            settings=settings,
        )
        duration = time.monotonic() - t0
    checks = [r.to_dict() for r in results]
    counts = {s: sum(c["status"] == s for c in checks) for s in doctor.STATUSES}
    return {
        "checked_at": time.time(),
        "duration_s": round(duration, 3),
        "live": live,
        "counts": counts,
        "checks": checks,
    }
