"""A run's end: how it ended, in its record, and what the dashboards are told.

Called once the loop process is gone and its outputs are safe (run_watch.wait_for_exit). In
order: the tasks that touch the shared memory stop; the run observers hear that the process is
gone (server/runs/lifecycle.py: host logging drains the rest of the log ring and records its counts); the
record gets its final state, counts and `end_reason` (runs.END_REASONS); the observers hear the
run ended; the shared memory is unlinked; the run's cgroup and file system are let go of (its
files kept, server/runs/limits.py). The supervisor then keeps the record as its last run
and `announce` tells the browsers: a crash or hang alarm with the safety watcher's times, the
`run` ended message and the inactive state.

`end_reason` decides the name: a hang first, then whoever ended the run on purpose (the limits
guard, a shutdown, another user), then a limit the run went over that the guard had not seen yet
(an OOM kill of the controller itself, SIGXCPU), then a stop that was asked for, then the exit
status and what the loop wrote about leaving its loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import time
from typing import NamedTuple

from ... import channels as chmod
from ...channels import ChannelsError
from ..settings import Settings
from ..ws.hub import Hub
from ..ws.messages import AlarmMessage
from . import hang_diag, watch_record
from .announce import ended
from .lifecycle import RunLifecycle
from .run import Run, remove_shm
from .store import END_REASONS, RunStore
from .watch import LIMIT_REASONS, publish_limit_alarm

log = logging.getLogger("xrflab.supervisor")

# The tasks that read the run's mapping, cancelled before it is let go (by the name's end).
MAPPING_TASKS = ("heartbeat", "reader", "timing", "limits")


class Ending(NamedTuple):
    """How the run's process ended, as recorded."""

    end_reason: str
    crashed: bool
    exit_code: int | None
    exit_signal: int | None


def end_reason(run: Run, returncode: int, last: chmod.Status | None) -> tuple[str, bool, str]:
    """(end_reason, crashed, crash_reason) of a run whose process ended with `returncode`;
    the names are runs.END_REASONS."""
    exit_signal = -returncode if returncode < 0 else 0
    loop_end = last.end_reason if last else chmod.lib.XRF_END_NONE
    if run.hang:
        return "hang", True, "hang"
    if run.end_reason:  # decided by whoever ended it (disk guard, shutdown, another user)
        return run.end_reason, False, ""
    if run.stop_requested and (returncode == 0 or exit_signal in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL)):
        return "stopped", False, ""
    if returncode != 0:
        return "crash", True, "signal" if exit_signal else "exit"
    if loop_end == chmod.lib.XRF_END_QUIT:
        return "quit", False, ""
    if loop_end == chmod.lib.XRF_END_CYCLE_LIMIT:
        return "cycle_limit", False, ""
    if loop_end == chmod.lib.XRF_END_SIGNAL:
        return "signal_stop", False, ""
    if loop_end == chmod.lib.XRF_END_RETURNED:
        return "returned", False, ""
    # exit(0) without leaving loop(): after STOP that is a program that simply ended; in any
    # other state (RUN above all) the controller walked away from a live machine.
    if last is not None and last.state in (chmod.lib.XRF_STATE_STOPPED, chmod.lib.XRF_STATE_QUIT):
        return "returned", False, ""
    if run.channels is None:
        return "start_failed", False, ""
    return "self_exit", True, "self_exit"


async def record(run: Run, returncode: int, settings: Settings, store: RunStore, lifecycle: RunLifecycle) -> Ending:
    """Everything up to the final record and the observers' `on_ended`; the shared memory is
    unlinked when it returns."""
    # Stop everything that touches the mapping before letting go of it.
    run.thread_stop.set()
    run.idle_wake.set()
    if run.thread is not None:
        await asyncio.to_thread(run.thread.join, 1.0)
    # The reader's last batch (server/runs/reader.py): the observers' samples since its last bulk
    # hand-over, or the 3D view's recording would lose the run's last second.
    readers = [t for t in run.tasks if t.get_name().endswith("reader") and not t.done()]
    if readers:
        run.wake.set()
        await asyncio.wait(readers, timeout=1.0)
    # Host logging drains the rest of the log ring (even after a crash) and records its counts
    # before the record says how the run ended (server/runs/lifecycle.py: on_exited).
    await lifecycle.exited(run)
    current = asyncio.current_task()
    for task in run.tasks:
        if task is not current and task.get_name().endswith(MAPPING_TASKS):
            task.cancel()
    status: chmod.Status | None = None
    if run.channels is not None:
        with contextlib.suppress(ChannelsError):
            status = run.channels.status()
    if status is not None:
        run.last_status = status
    exit_signal = -returncode if returncode < 0 else None
    exit_code = returncode if returncode >= 0 else None
    last = status or run.last_status
    if run.limits is not None and not run.hang and not run.end_reason:
        over = await asyncio.to_thread(run.limits.over, exit_signal or 0)
        if over is not None:
            run.end_reason = over[0]
            run.row = store.update(run.row.id, message=over[1])
    reason, crashed, crash_reason = end_reason(run, returncode, last)
    how = f"signal {signal.Signals(exit_signal).name}" if exit_signal else f"exit status {exit_code}"
    if run.row.message:
        message = run.row.message
    elif reason == "hang":
        message = f"loop hung (no cycle for > {settings.hang_timeout_ms} ms), killed"
    elif reason == "self_exit":
        state = last.state_name if last else "?"
        message = f"the controller ended by itself in {state} ({how}) without a stop or quit"
    else:
        message = f"loop process ended with {how} ({END_REASONS[reason]})"
    if reason == "hang":
        # Where the loop was when the watcher gave up on it (server/runs/hang_diag.py): its
        # verdict in the end note, the whole in the run's folder. Before the cgroup goes.
        message += await asyncio.to_thread(_diagnose_hang, run)
    safe_ms = (run.safe_at - run.exited_at) * 1000 if run.exited_at and run.safe_at >= run.exited_at else 0.0
    # A `hold` run's arm: what the watcher measured until it was at rest (the largest joint drop,
    # the time to rest), kept with the run as after an appliance's death (watch_record).
    outcome = watch_record.of_watch(run.watch_final) if run.watch_final is not None else None
    held = f"; {watch_record.describe(outcome)}" if outcome is not None else ""
    run.row = store.update(
        run.row.id,
        ended=time.time(),
        status="crashed" if crashed else ("ended" if run.channels is not None else "failed"),
        crashed=int(crashed),
        crash_reason=crash_reason,
        end_reason=reason,
        exit_code=exit_code,
        exit_signal=exit_signal,
        state=last.state_name if last else "",
        cycles=last.cycles if last else 0,
        misses=last.missed if last else 0,
        message=f"{message}; {run.safe_state}"
        + (f" {safe_ms:.1f} ms after exit" if crashed and not run.hang else "")
        + held,
        **({"safe_outcome": outcome} if outcome is not None else {}),
    )
    # The record is final: the observers in order (server/runs/lifecycle.py), then the browsers (announce).
    await lifecycle.ended(run.row, run)
    remove_shm(run.shm)  # its pages were charged to the run's cgroup: gone before the cgroup
    if run.shm_fd >= 0:  # the mapping stays valid without it
        os.close(run.shm_fd)
        run.shm_fd = -1
    if run.limits is not None:
        await asyncio.to_thread(run.limits.release)
        if run.limits.kept_note:
            run.row = store.update(run.row.id, message=f"{run.row.message}; {run.limits.kept_note}")
    # No explicit unmap: a worker thread may still hold the Channels (a command wait); the
    # mapping goes with the last reference, and the name is already unlinked.
    return Ending(reason, crashed, exit_code, exit_signal)


def _diagnose_hang(run: Run) -> str:
    """The hang's diagnosis: written to the run's folder, its summary for the end note ("" if
    the watcher recorded none: no watcher, or a loop already exiting)."""
    raw = run.watch.diagnosis if run.watch is not None else b""
    if not raw and run.watch_final is not None:
        raw = run.watch_final.diagnosis
    if not raw:
        return ""
    diag = hang_diag.parse(raw, run.row.pid or run.proc.pid)
    diag["counters"] = hang_diag.cgroup_counters(diag["cgroup"])
    diag["rt_throttle"] = hang_diag.rt_throttle()
    try:
        hang_diag.write(run.run_dir, diag)
    except (OSError, ValueError) as exc:  # RunPathError: the guest put something in its place
        log.warning("run %s: %s not written: %s", run.row.id, hang_diag.RECORD, exc)
    log.warning("run %s hung: %s", run.row.id, diag["verdict"])
    return f"; {hang_diag.summary(diag)}"


def announce(run: Run, ending: Ending, hub: Hub) -> None:
    """Tell the browsers (after the record is final and kept as the last run), mark the run
    ended, and let go of what it held."""
    if ending.crashed:
        hub.publish(
            AlarmMessage(
                kind="hang" if run.hang else "crash",
                end_reason=ending.end_reason,
                run_id=run.row.id,
                message=run.row.message,
                exit_code=ending.exit_code,
                exit_signal=ending.exit_signal,
                safe_state=run.safe_state,
                # From the safety watcher (CLOCK_MONOTONIC ns): when it saw the exit or hang and
                # when the outputs were safe; 0 where no watcher ran.
                event_ns=run.watch.event_ns if run.watch else 0,
                safe_ns=run.watch.safe_ns if run.watch else 0,
                heartbeat_ns=run.watch.heartbeat_ns if run.watch else 0,  # the loop's last cycle start
                watcher_rt=bool(run.watch and run.watch.rt_status == 0),
            )
        )
    if ending.end_reason in LIMIT_REASONS:
        # Over a limit the guard had not seen before the end (the kernel killed the controller).
        publish_limit_alarm(run, ending.end_reason, run.row.message, hub)
    run.ended.set()
    for message in ended(run):
        hub.publish(message)
    # Let go of the run's tasks and log writer now: a cancelled task's traceback holds its
    # frames, whose locals hold the run's 10 MB mapping; left to the cyclic GC, a lab day of
    # crashes kept dozens of them (and their descriptors) alive.
    run.tasks.clear()
    run.logging = None
    run.report_corrupt = None  # its closure holds the run: a cycle, left to the GC otherwise
