"""Reading a live run for the dashboards: telemetry and monitor lines when the loop rings the
doorbell, the loop's printed output as it grows.

The loop rings a futex doorbell in its shared memory after every cycle it published something
in. A thread of our own sleeps in that futex (`doorbell_thread`) so the event loop never polls;
it wakes the reader task, coalescing bursts into one wake-up. The reader hands every sample to
the run observers (server/runs/lifecycle.py: the 3D view) and sends the dashboards a decimated stream
(``telemetry_hz``), the monitor ring's lines and, when it changed, the state.

The controller's stdout/stderr go to a file in the run folder (a pipe would SIGPIPE the loop if
the appliance died); `pipe_output` follows it for the console. `guarded` restarts a reader-type
task after an unexpected error instead of losing the stream for the rest of the run.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from typing import Any, Literal

from ...channels import ChannelsCorrupt
from ..ws.hub import Hub
from ..ws.messages import MonitorLine, MonitorMessage, TelemetryMessage
from .announce import refresh_state
from .launch import open_output
from .lifecycle import RunLifecycle
from .output_lines import OutputLines
from .run import Run

log = logging.getLogger("xrflab.supervisor")
DOORBELL_WAIT_MS = 50  # also the fallback poll period if a loop never rings
READS_PER_POLL = 64  # 4 MiB of output per poll at most, then the event loop gets its turn


def doorbell_thread(run: Run, loop: asyncio.AbstractEventLoop) -> None:
    """Blocks in the futex wait so the event loop never polls; wakes the reader task."""
    ch = run.channels
    assert ch is not None
    seen = ch.doorbell
    while not run.thread_stop.is_set():
        seen = ch.wait_doorbell(seen, DOORBELL_WAIT_MS)
        if not run.wake_pending:  # coalesce: one pending wake-up is enough
            run.wake_pending = True
            try:
                loop.call_soon_threadsafe(run.wake.set)
            except RuntimeError:  # event loop closed (shutdown)
                return


async def read(run: Run, telemetry_hz: float, lifecycle: RunLifecycle, hub: Hub) -> None:
    """The reader task: one batch per doorbell wake-up, until cancelled at the run's end."""
    ch = run.channels
    assert ch is not None
    telemetry = ch.telemetry_reader()
    monitor = ch.monitor_reader()
    period_ns = int(1e9 / telemetry_hz) if telemetry_hz > 0 else 0
    next_due_ns = 0
    run_id = run.row.id
    t0 = 0  # the loop's first deadline (status t_start_ns): set once by cycle 1, read once here
    # The Ros2Xeno the loop has, read from its shared memory once per batch that sends telemetry:
    # whoever wrote it (this appliance, the ROS 2 bridge, a CLI), the Watch page shows the loop's.
    ros2xeno: dict[str, Any] = {}
    while True:
        await run.wake.wait()
        run.wake.clear()
        run.wake_pending = False
        samples = telemetry.read()
        if samples:
            lifecycle.samples(run, samples)  # the run observers (3D view, ...) take every sample
        # Dashboards' streams: built only when a client (or a hub listener) takes them. The rings
        # are read either way, so a client that connects gets new samples and lines, not a
        # backlog, and the `lost` counters keep meaning the loop's losses.
        if samples and hub.wants("telemetry"):
            if not t0:
                t0 = ch.status().t_start_ns
            ros2xeno = ch.read_ros2xeno() or ros2xeno  # None: a write in progress, keep the last
            for sample in samples:
                # Credit-based decimation: the average rate is telemetry_hz exactly even when the
                # loop's own rate is not a multiple of it (100 Hz -> 30 Hz sends 3 of every 10).
                if period_ns:
                    if sample.t_ns < next_due_ns:
                        continue
                    next_due_ns = max(next_due_ns + period_ns, sample.t_ns - period_ns)
                run.telemetry_sent += 1
                # Validated like every message: at telemetry_hz (30 Hz) building and checking the
                # model costs a few microseconds, and model_construct() is no cheaper in pydantic 2.
                hub.publish(
                    TelemetryMessage(
                        run_id=run_id,
                        cycle=sample.cycle,
                        t_ns=sample.t_ns,
                        t=(sample.t_ns - t0) / 1e9 if t0 else sample.t_ns / 1e9,
                        state=sample.state,
                        enc=sample.enc,
                        din=sample.din,
                        pwm=sample.pwm,
                        dout=sample.dout,
                        xeno2ros=sample.xeno2ros,
                        ros2xeno=ros2xeno,
                        ros2xeno_t_sent_ns=sample.ros2xeno_t_sent_ns,
                        lost=telemetry.lost,
                    )
                )
        lines = monitor.read()
        if lines and hub.wants("monitor"):
            hub.publish(
                MonitorMessage(
                    run_id=run_id,
                    source="monitor",
                    lines=[MonitorLine(cycle=m.cycle, t_ns=m.t_ns, text=m.text) for m in lines],
                    lost=monitor.lost,
                )
            )
        refresh_state(run, hub)


async def pipe_output(run: Run, hub: Hub) -> None:
    """Follow the loop's stdout/stderr file into the monitor console. Polled every 100 ms:
    this is for people reading, nothing safety-related waits on it. What the guest printed is
    bounded on the way (server/runs/output_lines.py): long lines are cut, floods are counted, not queued."""
    cutter = OutputLines()

    def publish(lines: list[str], source: Literal["stdout", "appliance"] = "stdout") -> None:
        if lines:
            hub.publish(MonitorMessage(run_id=run.row.id, source=source, lines=[MonitorLine(text=t) for t in lines]))

    def say_skipped() -> None:
        skipped = cutter.take_skipped()
        if skipped:
            note = f"appliance: {skipped} lines of output not shown here (too many at once); output.txt has them"
            publish([note], "appliance")

    with open_output(run.run_dir) as f:  # through the run folder's helper: never a link the loop put there
        while True:
            alive = run.alive  # sampled before reading, so the last output is not missed
            lines: list[str] = []
            # Catch up with the file, a bounded amount per poll so a flood cannot hold the event
            # loop; the console gets at most lines_per_poll of it.
            for _ in range(READS_PER_POLL):
                chunk = f.read(65536)
                cutter.feed(chunk, lines)
                if len(chunk) < 65536:
                    break
            caught_up = len(chunk) < 65536
            if caught_up and not alive:
                cutter.flush(lines)
            publish(lines)
            say_skipped()
            if caught_up and not alive:
                return
            await asyncio.sleep(0.1 if caught_up else 0.01)


async def guarded(name: str, body: Callable[[], Awaitable[None]], run: Run, hub: Hub) -> None:
    """Restart a reader-type task after an unexpected error (a sample the codec cannot
    decode, say) instead of silently losing telemetry for the rest of the run. `name` is how
    the console names the task ("appliance: <name> failed: ...")."""
    while not run.ended.is_set():
        try:
            await body()
            return
        except asyncio.CancelledError:
            raise
        except ChannelsCorrupt as exc:
            # Not a bug to retry: the loop broke its segment. The run is stopped (server/runs/corrupt.py)
            # and nothing of the segment is read here again.
            if run.report_corrupt is not None:
                run.report_corrupt(exc)
            return
        except Exception as exc:  # reported to the dashboards, then carry on
            log.exception("run %s: %s failed", run.row.id, name)
            hub.publish(
                MonitorMessage(
                    run_id=run.row.id,
                    source="appliance",
                    lines=[MonitorLine(text=f"appliance: {name} failed: {exc!r}")],
                )
            )
            await asyncio.sleep(0.5)
