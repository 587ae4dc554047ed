"""Launching a run's loop process: its environment, its sandbox, its shared memory.

The controller never sees the appliance's own environment: it gets an allow-list
(guest.ENV_ALLOWED; docs/developers/architecture.md lists the variables) and starts inside the
run sandbox (server/runs/guest_spawn.py: own uid, namespaces, limits; docs/developers/security.md). Its
output goes to a file in the run folder, not a pipe to us: if the appliance dies, a pipe would
turn the loop's next printf into SIGPIPE; a file keeps it running, and kept.

Before the launcher starts, the run gets what the kernel bounds (server/runs/limits.py): its cgroup
(memory with its /dev/shm, processes, CPUs) and its run folder as a file system of its own.

A run starts only with every protection layer of the sandbox in place unless an educator allowed
otherwise; a refused start is recorded (``start_failed``) and raised as `StartRefused`, whose
confinement alarm the supervisor publishes once it has kept the record. A started run is mapped
(`open_channels`) once the loop marks its shared memory ready, unless the process dies first.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from pathlib import Path
from typing import BinaryIO

from ... import guest, plants
from ...channels import Channels, ChannelsCorrupt, StatusBusy, segment
from ...logs import live as loglive
from ...runfolder import open_in
from ..settings import Settings
from ..ws.hub import Hub
from ..ws.messages import AlarmMessage
from . import disk as run_disk
from .catalog import BuildEntry
from .control import terminate
from .guest_spawn import GuestReport, GuestSpawner
from .limits import NoRoom, RunLimits
from .run import SEGMENT_LINK_SUFFIX, Run, SupervisorError, remove_shm
from .store import RunRow, RunStore

log = logging.getLogger("xrflab.supervisor")
OUTPUT = "output.txt"  # the controller's stdout and stderr, in its run folder


def open_output(run_dir: Path) -> BinaryIO:
    """The controller's output.txt for reading (the console follows it): through the run
    folder's helper, our own file only, so a link (to /etc/shadow, say) or a FIFO the loop put
    in its place is never followed; an empty stream when it is refused."""
    try:
        return os.fdopen(open_in(run_dir, OUTPUT, own=True), "rb")
    except (OSError, ValueError) as exc:
        log.warning("%s: the loop's output is not followed: %s", run_dir, exc)
        return open(os.devnull, "rb")


class StartRefused(SupervisorError):
    """The sandbox refused to start the controller (a protection layer missing, not allowed);
    `row` is the run's final record, `report` says which layers hold."""

    def __init__(self, message: str, row: RunRow, report: GuestReport) -> None:
        super().__init__(message, 503)
        self.row = row
        self.report = report


def loop_env(
    settings: Settings, run_id: int, build: str, plant: str, run_dir: Path, max_cycles: int | None, log_timing: bool
) -> dict[str, str]:
    """The loop process's whole environment: an allow-list, never a copy of our own
    (xrflab.guest.ENV_ALLOWED)."""
    env = {
        "PATH": "/usr/local/bin:/usr/bin:/bin",
        "LANG": "C.UTF-8",
        "HOME": str(run_dir),
        "TMPDIR": "/tmp",
        "XRF_SHM": guest.SHM_NAME,
        "XRF_SIM": plant,
        "XRF_LOG_DIR": str(run_dir),
        "XRF_HOST_TIMEOUT_MS": str(settings.host_timeout_ms),
        "XRF_HOST_TIMEOUT_ACTION": settings.host_timeout_action,
        # We read monitor lines from the ring; the process echoing them to stdout as well
        # would show every line twice in the console.
        "XRF_QUIET": "1",
    }
    env.update(loglive.loop_env(run_id, build, log_timing))
    if not settings.bench_is_real():
        env["XRF_TRANSPORT"] = "sim"
    else:  # every board's device, board 1 first (rt_core's spidev transport opens one per board)
        env["XRF_SPI_DEVICE"] = ",".join(settings.spi_bench())
    if max_cycles:
        env["XRF_MAX_CYCLES"] = str(max_cycles)
    env.update({k: v for k, v in settings.loop_env.items() if k in guest.ENV_ALLOWED})
    return env


async def spawn(
    row: RunRow,
    entry: BuildEntry,
    plant: str,
    max_cycles: int | None,
    log_timing: bool,
    settings: Settings,
    guests: GuestSpawner,
    store: RunStore,
) -> Run:
    """Start `entry`'s controller for the run `row` (just created) in its sandbox; the Run,
    its record saying ``starting``. Raises SupervisorError (500) when the sandbox could not be
    set up, StartRefused (503) when it refused the controller."""
    assert entry.executable is not None
    shm_dir = guests.shm_dir_for(f"xrf-lab-{os.getpid()}-{row.id}")  # the loop's /dev/shm
    # The run's segment is ours (a sealed memfd: the loop cannot resize it under our mapping);
    # its name is a link beside the loop's folder, out of the loop's reach (segment_link).
    # The bench's channel count goes into the segment's header: the loop keeps it, and every
    # reader takes it from there, bounded (the simulated plant's row; a real bench is one board).
    channels = plants.get(plant).channels if not settings.bench_is_real() else None
    shm_fd = segment.create_sealed(f"xrf-run-{row.id}", channels)
    shm = segment_link(shm_dir, shm_fd)
    run_dir = settings.runs_dir / str(row.id)
    run_dir.mkdir(parents=True, exist_ok=True)
    row = store.update(row.id, shm=shm, run_dir=str(run_dir))
    env = loop_env(settings, row.id, entry.name, plant, run_dir, max_cycles, log_timing)
    limits: RunLimits | None = None
    env["XRF_SHM_FD"] = str(shm_fd)

    def let_go() -> None:
        os.close(shm_fd)
        remove_shm(shm)  # the link and the loop's folder

    try:
        # First the kernel's bounds (the run folder becomes its own file system), then the folders'
        # owners and modes, then the output file inside it: the controller's stdout counts too.
        limits = await guests.prepare_limits(
            guests.cgroup_name(row.id), run_dir, run_disk.image_for(settings.data_dir, row.id)
        )
        guests.prepare_dirs(run_dir, shm_dir)
        # Made before the controller exists, and ours (the console reads it back: pipe_output).
        with os.fdopen(open_in(run_dir, OUTPUT, os.O_WRONLY | os.O_CREAT | os.O_APPEND, own=True), "ab") as output:
            proc, report = await guests.spawn(
                entry.executable,
                run_dir,
                shm_dir,
                env,
                [entry.executable.parent],
                output,
                tag=shm,
                timeout_s=settings.open_timeout_s,
                limits=limits,
                shm_fd=shm_fd,
            )
    except NoRoom as exc:
        let_go()
        store.update(row.id, status="failed", end_reason="start_failed", ended=time.time(), message=f"disk: {exc}")
        raise SupervisorError(f"no room for another run: {exc}", 507) from exc
    except (OSError, ValueError, RuntimeError, asyncio.TimeoutError) as exc:
        await _let_go(limits)
        let_go()
        store.update(row.id, status="failed", end_reason="start_failed", ended=time.time(), message=f"sandbox: {exc}")
        raise SupervisorError(f"cannot start {entry.executable.name} in its sandbox: {exc}", 500) from exc
    if report.error:
        await proc.wait()
        await _let_go(limits)
        let_go()
        final = store.update(
            row.id,
            status="failed",
            end_reason="start_failed",
            ended=time.time(),
            message=f"sandbox: {report.error}",
        )
        raise StartRefused(f"the controller was not started: {report.error}", final, report)
    # The controller's own pid (what `kill` or a test would aim at); we wait on the launcher.
    row = store.update(row.id, pid=report.pid or proc.pid, status="starting")
    return Run(
        row=row,
        proc=proc,
        shm=shm,
        run_dir=run_dir,
        build=entry,
        log_timing=log_timing,
        guest=report,
        limits=limits,
        shm_fd=shm_fd,
    )


async def _let_go(limits: RunLimits | None) -> None:
    """A start that failed: its run folder keeps what was written (the refusal in output.txt)."""
    if limits is not None:
        await asyncio.to_thread(limits.release)


def segment_link(shm_dir: Path, shm_fd: int) -> str:
    """A name for the run's segment (a memfd has none) for whoever opens it by name as before --
    the ROS 2 bridge, `xrf` commands, tests: a symlink beside the loop's /dev/shm folder (so the
    loop, which sees only that folder, cannot replace it) to /proc/<appliance>/fd/<shm_fd>. The
    kernel lets only the appliance's own user follow it (ptrace access); it dangles once the
    appliance lets go of the segment. Returns the name below /dev/shm (shm_path)."""
    name = shm_dir.name + SEGMENT_LINK_SUFFIX
    link = shm_dir.parent / name
    with contextlib.suppress(FileNotFoundError):
        link.unlink()  # a leftover of a dead appliance with the same pid
    os.symlink(f"/proc/{os.getpid()}/fd/{shm_fd}", link)
    return name


def announce_refused(refused: StartRefused, hub: Hub) -> None:
    hub.publish(
        AlarmMessage(
            kind="confinement",
            run_id=refused.row.id,
            message=refused.report.error,
            missing=refused.report.missing,
            started=False,
        )
    )


def announce_unconfined(run: Run, hub: Hub) -> None:
    """A run started without some protection layer (an educator allowed it): everyone is told
    which (the dashboard's banner)."""
    report = run.guest
    if report is None or not report.missing:
        return
    hub.publish(
        AlarmMessage(
            kind="confinement",
            run_id=run.row.id,
            missing=report.missing,
            started=True,
            message="the controller runs WITHOUT: " + "; ".join(f"{k} ({v})" for k, v in report.missing.items()),
        )
    )


async def open_channels(run: Run, settings: Settings, store: RunStore) -> bool:
    """Map the run's shm once the loop marks it ready, unless the process dies first."""

    def open_segment(wait_s: float) -> Channels:
        if run.shm_fd >= 0:  # the sealed memfd launch.spawn made
            return Channels.open_fd(run.shm_fd, run.shm, wait_s)
        return Channels.open(run.shm, wait_s)

    opening = asyncio.ensure_future(asyncio.to_thread(open_segment, settings.open_timeout_s))
    # The process's exit, not the run's end: the end waits for the start (Run.settled). A segment
    # made ready by a loop that has ended since is still opened: its log is drained at the end.
    exited = asyncio.ensure_future(run.proc.wait())
    done, _ = await asyncio.wait({opening, exited}, return_when=asyncio.FIRST_COMPLETED)
    exited.cancel()
    ended_first = opening not in done
    if ended_first:
        # The loop ended first. A short run (`max_cycles`) marks its segment ready and ends within
        # milliseconds, before the opening's next look: ready now means ready for good (the
        # loop is gone), so one look without waiting says whether it ran.
        opening.add_done_callback(lambda f: f.exception())  # let the waiting thread finish quietly
        opening = asyncio.ensure_future(asyncio.to_thread(open_segment, 0.0))
        await asyncio.wait({opening})
    if opening.exception() is None:
        ch = opening.result()
        run.channels = ch
        ch.configure_host_timeout(settings.host_timeout_ms, settings.host_timeout_action)
        with contextlib.suppress(StatusBusy):  # mid-write: refresh_state takes it later
            run.last_status = ch.status()
        return True
    if isinstance(opening.exception(), ChannelsCorrupt) and run.report_corrupt is not None:
        # Ready, but not a segment our runtime writes (a ring's geometry, the info block): the
        # run is stopped as any run that breaks its segment (server/runs/corrupt.py).
        exc = opening.exception()
        assert isinstance(exc, ChannelsCorrupt)
        run.report_corrupt(exc)
        return False
    if not ended_first:  # the loop never made its shm ready: treat as a failed start
        message = f"loop did not open its shared memory: {opening.exception()}"
        run.row = store.update(run.row.id, message=message)
        run.settled.set()  # the start gives up: the end may follow (terminate waits for it)
        await terminate(run, settings)
    return False  # (ended before its segment was ready: the end says how it ended)
