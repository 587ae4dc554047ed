"""Watching a live run from outside: its safety watcher, the heartbeats, its disk use, its exit.

Safety: every run with open shared memory has a safety watcher (server/safety.py, rt_core's
watch.c): a C thread outside the event loop, woken by the kernel when the loop process exits, that
checks the loop's heartbeat every few milliseconds. On an exit, or a hang (no cycle for
``hang_timeout_ms``: it kills the loop), it puts the outputs in a safe state first (the simulated
board's ``forced_off``, or an FPGA RESET over spidev on a real bench) and only then tells us
through an eventfd (`on_watch`). A busy event loop delays the record, never the safe outputs.

The heartbeat task writes the host heartbeat the loop checks (XRF_HOST_TIMEOUT_MS: the loop
pauses itself if the appliance dies or hangs) and, only where no watcher could start, detects a
hang itself. The disk guard stops a run whose folder outgrows the sandbox's limit. `wait_for_exit`
is the run's last word: the launcher's exit, the watcher's account of it, and safe outputs where
no watcher made them so; run_end.py then records how the run ended.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import time

from ..channels import ChannelsError
from ..logs.runfolder import folder_bytes
from .hub import Hub
from .messages import AlarmMessage
from .run import Run
from .run_control import terminate
from .runs import RunStore
from .safety import SafetyWatcher, WatchResult, fpga_reset
from .settings import Settings

log = logging.getLogger("xrflab.supervisor")


# ---- the safety watcher -------------------------------------------------------------------------


def start_watcher(run: Run, settings: Settings) -> None:
    """The safety watcher for a run whose shared memory is open (safety.py)."""
    ch = run.channels
    assert ch is not None
    info = ch.info
    # A slow loop (10 Hz) beats less often than the default timeout: a hang is three
    # missed periods at the least, never one long cycle.
    period_ms = 1000 // max(1, int(info.get("cycle_freq", 0)) or 1)
    hang_ms = max(settings.hang_timeout_ms, 3 * period_ms)
    # Below the loop's real-time priority, above everything else we run.
    loop_prio = int(info.get("priority", 0))
    prio = min(settings.watch_priority, loop_prio - 1) if loop_prio > 1 else settings.watch_priority
    real = settings.bench_is_real()
    try:
        w = SafetyWatcher(
            run.row.pid or run.proc.pid,
            ch,
            hang_timeout_ms=hang_ms,
            check_ms=max(2, min(20, hang_ms // 10)),
            force_sim=info.get("transport", "sim") == "sim",
            spi_device=settings.spi_device if real else "",
            rt_priority=max(0, prio),
        )
    except (OSError, ValueError) as exc:  # ESRCH: the loop is already gone; wait_for_exit handles it
        log.warning("run %s: no safety watcher (%s); the event loop watches instead", run.row.id, exc)
        return
    run.watcher = w
    asyncio.get_running_loop().add_reader(w.fileno(), on_watch, run)


def on_watch(run: Run) -> None:
    """The watcher acted (outputs already safe): take note. The record follows the exit."""
    w = run.watcher
    if w is None:
        return
    with contextlib.suppress(ValueError, OSError):
        asyncio.get_running_loop().remove_reader(w.fileno())
    result = w.result()
    if result is not None:
        take_watch(run, result)


def take_watch(run: Run, result: WatchResult) -> None:
    if not result.acted or run.watch is not None:
        return
    run.watch = result
    run.safe_state = result.describe()
    run.exited_at = result.event_ns / 1e9
    run.safe_at = result.safe_ns / 1e9
    if result.reason == "hang":
        run.hang = True
        if result.kill_status != 0:  # could not kill it through the pidfd: the launcher can
            with contextlib.suppress(ProcessLookupError):
                run.proc.send_signal(signal.SIGKILL)


def safe_state(run: Run, settings: Settings) -> None:
    """Outputs off where no watcher did it (the loop died before its memory was open, or the
    watcher could not start)."""
    if run.safe_state:
        return
    transport = run.channels.info.get("transport", "sim") if run.channels else ""
    if run.channels is not None and transport == "sim":
        run.channels.force_sim_outputs_off()
        run.safe_state = "sim outputs forced off"
    elif settings.bench_is_real():
        run.safe_state = fpga_reset(settings.spi_device)
    else:
        # The simulated board lives inside the loop process: with no shm it died with it.
        run.safe_state = "simulated board ended with the process"
    run.safe_at = time.monotonic()


async def wait_for_exit(run: Run, settings: Settings) -> int:
    """Wait for the loop process to end; its return code, once the outputs are safe."""
    returncode = await run.proc.wait()
    if run.watcher is not None:
        w = run.watcher
        with contextlib.suppress(ValueError, OSError):
            asyncio.get_running_loop().remove_reader(w.fileno())
        # The exit has happened: stop() lets the thread handle it first if it has not yet.
        take_watch(run, await asyncio.to_thread(w.stop))
    if not run.exited_at:
        run.exited_at = time.monotonic()
    safe_state(run, settings)
    return returncode


# ---- heartbeats ---------------------------------------------------------------------------------


async def heartbeat(run: Run, settings: Settings) -> None:
    """Host heartbeat out, loop heartbeat in (hang detection where no watcher runs)."""
    ch = run.channels
    assert ch is not None
    hang_ns = settings.hang_timeout_ms * 1_000_000
    last_good = time.monotonic_ns()
    while run.alive:
        ch.host_heartbeat()
        now = time.monotonic_ns()
        try:
            s = ch.status()
        except ChannelsError:
            s = None  # seqlock held: a loop stopped mid-write looks exactly like this
        if s is not None:
            run.last_status = s
            stale = s.running and s.heartbeat_ns > 0 and now - s.heartbeat_ns > hang_ns
            if not stale:
                last_good = now
        if run.watcher is None and now - last_good > hang_ns and run.alive:
            run.hang = True
            safe_state(run, settings)
            run.exited_at = time.monotonic()
            with contextlib.suppress(ProcessLookupError):
                run.proc.send_signal(signal.SIGKILL)
            return
        await asyncio.sleep(min(settings.host_heartbeat_period_s, settings.hang_timeout_ms / 4000))


# ---- disk use -----------------------------------------------------------------------------------


async def disk_guard(run: Run, limit: int, settings: Settings, store: RunStore, hub: Hub) -> None:
    """The run folder's disk use stays under `limit` bytes (the sandbox's): beyond it the run is
    stopped (the controller's own files; the appliance's log writer has its own full-disk
    handling)."""
    while run.alive and not run.ended.is_set():
        await asyncio.sleep(2.0)
        # The run folder is the loop's: walked through its helper, entered by descriptor only.
        used = await asyncio.to_thread(folder_bytes, run.run_dir)
        if used > limit and run.alive:
            message = f"the run folder holds {used >> 20} MB, over the limit of {limit >> 20} MB: run stopped"
            run.row = store.update(run.row.id, message=message)
            hub.publish(AlarmMessage(kind="disk", run_id=run.row.id, message=message))
            run.stop_requested = True
            run.end_reason = "disk"
            await terminate(run, settings)
            return
