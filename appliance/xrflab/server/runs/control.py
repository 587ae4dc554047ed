"""Talking to a live run: commands and setpoints in, and ending it in order.

A command goes through the loop's command ring (channels.h) and is answered by the loop itself,
which alone knows whether its state machine accepts it; the appliance only waits for the answer
and publishes the state at once, so every dashboard sees the outcome without waiting for the
next sample. Setpoints are the run's Ros2Xeno message, written whole (latest wins).

Ending a run asks before it forces: stop (from RUN or PAUSED), then quit, each waiting for the
loop to get there, so the controller's own hooks leave the outputs off; only a loop that does not
answer gets SIGINT (the runtime's safe stop), then SIGTERM, then SIGKILL.
"""

from __future__ import annotations

import asyncio
import contextlib
import signal
import time
from typing import Any

from ... import channels as chmod
from ...channels import ChannelsCorrupt, ChannelsError, StatusBusy
from ..settings import Settings
from ..ws.hub import Hub
from .announce import refresh_state
from .run import Run, SupervisorError
from .store import RunStore

STATE_RUN = chmod.lib.XRF_STATE_RUN
STATE_PAUSED = chmod.lib.XRF_STATE_PAUSED
STATE_STOPPED = chmod.lib.XRF_STATE_STOPPED
STATE_ERROR = chmod.lib.XRF_STATE_ERROR
# States a loop passes through on its own (a hook completing): wait for them to settle.
SETTLING = {
    chmod.lib.XRF_STATE_INITIALISING,
    chmod.lib.XRF_STATE_STOPPING,
    chmod.lib.XRF_STATE_PAUSING,
}
SOURCE_APPLIANCE = chmod.lib.XRF_SOURCE_APPLIANCE


def active(run: Run | None) -> Run:
    """`run` if it can take a command now (its loop lives and its shared memory is open)."""
    if run is None or not run.alive or run.ended.is_set():
        raise SupervisorError("no run is active; start one first")
    if run.channels is None:
        raise SupervisorError("the run is still starting")
    return run


async def command(run: Run, number: int, hub: Hub) -> chmod.CommandResult:
    """Queue a command, wait until the loop handled it, publish the state at once."""
    ch = run.channels
    assert ch is not None
    try:
        ticket = ch.send_command(number, source=SOURCE_APPLIANCE)
    except ChannelsCorrupt as exc:
        if run.report_corrupt is not None:
            run.report_corrupt(exc)
        raise SupervisorError(f"the run is being stopped: {exc}") from None
    try:
        result = await asyncio.to_thread(ch.wait_command, ticket, 2.0)
    finally:
        if not run.ended.is_set():
            refresh_state(run, hub)
    return result


def setpoint(run: Run, fields: dict[str, Any]) -> dict[str, Any]:
    """Merge into the run's Ros2Xeno (latest wins, so the whole message is written). Merged into
    what the loop has, not what this appliance last wrote: a field the ROS 2 bridge or another
    writer set since is kept, not taken back to an old value."""
    ch = run.channels
    assert ch is not None
    merged = {**(ch.read_ros2xeno() or run.setpoint), **fields}
    ch.write_ros2xeno(merged)  # ValueError on unknown fields or bad values
    run.setpoint = merged
    return merged


async def stop(run: Run, by: str, settings: Settings, store: RunStore) -> None:
    """Stop the run in order and wait for its end. `by`: who asked (a username): someone other
    than the run's owner (an educator, a self-check) is named in the run's end."""
    run.stop_requested = True
    if by and run.row.owner and by.strip().lower() != run.row.owner.strip().lower() and not run.end_reason:
        run.end_reason = "stopped_by_other"
        run.row = store.update(run.row.id, message=f"stopped by {by}")
    await graceful_stop(run, settings)
    if not run.ended.is_set():
        await terminate(run, settings)
    await run.ended.wait()


async def graceful_stop(run: Run, settings: Settings) -> None:
    """stop (from RUN/PAUSED), then quit, each waiting for the loop to get there."""
    ch = run.channels
    if ch is None or not run.alive:
        return
    timeout = settings.stop_state_timeout_s
    try:
        state = await settled_state(run, timeout)
        if state in (STATE_RUN, STATE_PAUSED):
            ch.send_command("stop", source=SOURCE_APPLIANCE)
            state = await settled_state(run, timeout, want={STATE_STOPPED, STATE_ERROR})
        if state in (STATE_STOPPED, STATE_ERROR):
            ch.send_command("quit", source=SOURCE_APPLIANCE)
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(asyncio.shield(run.ended.wait()), timeout)
    except ChannelsError:
        pass  # command ring full or status locked: fall through to signals


async def settled_state(run: Run, timeout: float, want: set[int] | None = None) -> int:
    """The loop's state once it is one of `want` (default: not passing through), or at the
    timeout, or when the loop is gone."""
    ch = run.channels
    assert ch is not None
    deadline = time.monotonic() + timeout
    while True:
        try:
            state = ch.status().state
            done = state in want if want else state not in SETTLING
        except StatusBusy:  # the loop mid-write and no copy read yet: ask again
            state, done = -1, False
        if done or time.monotonic() > deadline or not run.alive:
            return state
        await asyncio.sleep(0.005)


async def terminate(run: Run, settings: Settings) -> None:
    """SIGINT (the runtime's safe stop), then SIGTERM, then SIGKILL."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
        if not run.alive:
            break
        with contextlib.suppress(ProcessLookupError):
            run.proc.send_signal(sig)
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(asyncio.shield(run.ended.wait()), settings.signal_timeout_s)
        if run.ended.is_set():
            break
