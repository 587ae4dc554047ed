"""Reading a live run for the dashboards: telemetry and monitor lines when the loop rings the
doorbell, the loop's printed output as it grows.

The loop rings a futex doorbell in its shared memory after every cycle it published something
in. The reader task reads a batch (telemetry, monitor lines, the state) at each of its wake-ups,
and wakes in one of three ways (issue 30 item 4: how often a Python process wakes is most of
what it costs on a busy core):

- With nobody taking the run's streams (telemetry, monitor lines, state) it wakes itself on the
  event loop's clock every `idle_period`, a quarter of the time the telemetry and monitor rings
  take to fill at the rate it last saw (at most IDLE_PERIOD_S, on the whole seconds of
  xrflab/ticks.py), so every sample still reaches the run observers (the 3D view's recording)
  and nothing is overwritten unread; a client that connects wakes it at once
  (Supervisor._client_connected), and so does a 3D view that starts to be watched.
- With a dashboard taking telemetry it wakes itself just after the loop publishes the sample
  that completes the next message (`next_publication` + TIMED_MARGIN_NS: the loop publishes at
  a fixed spacing on our monotonic clock; a message is `per_message` samples due, 6 by default),
  so it wakes ~5 times a second for a RELbot (dashboards get 30 samples a second of its 50, six
  a message), the newest sample of each message read within about a millisecond of its
  publication, and neither a thread of ours nor the event loop's self-pipe is woken for the
  samples in between. What the loop published before it (samples, monitor lines, a state
  change of its own) is read in that batch, at most one message period (200 ms) later; a
  command's state is published when the loop took it (server/runs/control.py), not here.
- With clients that take monitor lines or the state but not telemetry (a dashboard tab that is
  hidden, a tool), or a 3D view watched with no dashboard, it wakes itself every
  STREAMS_PERIOD_S (10 times a second, sooner should a ring fill faster): the doorbell would
  wake it for every publication of the loop (50 a second for a RELbot), more often than a
  visible dashboard does. A 3D view that starts to be watched wakes it at once
  (Supervisor.wake_reader), so its model and trail are current from then on.
- Otherwise it follows the doorbell: a thread of our own sleeps in that futex
  (`doorbell_thread`) and wakes the reader, coalescing bursts into one wake-up. That is where
  the publications' spacing is not known (the first samples, simulated time, whose clock is not
  ours) and when the sample due came late (the reader woke and it was not there: the next ring
  brings it). In the other cases the thread is parked outside the futex (`Run.reader_timed`):
  the loop then has no waiter to wake either (no system call in its doorbell path).

The reader hands every sample to the run observers (server/runs/lifecycle.py: the 3D view) and
sends the dashboards a decimated stream (``telemetry_hz`` samples a second, ``per_message`` of them
a message, oldest first), the monitor ring's lines and, when it changed, the state.

The controller's stdout/stderr go to a file in the run folder (a pipe would SIGPIPE the loop if
the appliance died); `pipe_output` follows it for the console. `guarded` restarts a reader-type
task after an unexpected error instead of losing the stream for the rest of the run.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from collections.abc import Awaitable, Callable
from typing import Any, BinaryIO, Literal

from ...channels import ChannelsCorrupt, StatusBusy
from ...ticks import until_aligned
from ..ws.hub import Hub
from ..ws.messages import MonitorLine, MonitorMessage, TelemetryMessage
from .announce import STATUS_REFRESH_S, refresh_state
from .launch import open_output
from .lifecycle import RunLifecycle
from .output_lines import OutputLines
from .run import Run

log = logging.getLogger("xrflab.supervisor")
DOORBELL_WAIT_MS = 50  # also the fallback poll period if a loop never rings
# Longest wait between two reads with nobody taking the streams: what it reads then is the 3D
# view's recording and model (in bulk, viz/scene.py), which nobody watches; 4 s of a RELbot's
# samples is 200 of the telemetry ring's 1024 (idle_period keeps it under a quarter of any ring).
# The run's status for the REST routes and the room stays a second old at most (the timing task
# refreshes it: server/runs/timing.py). It was 1 s (issue 30 item 4: the reader's idle batch
# was half the idle event loop's Python).
IDLE_PERIOD_S = 4.0
IDLE_MIN_S = DOORBELL_WAIT_MS / 1000
RING_MARGIN = 4  # the idle wait lets a ring fill to a quarter at most
LIVE_RECHECK_S = 0.25  # how often the reader asks whether the run observers are watched
# The reader's period for clients taking the state or monitor lines but not telemetry: a state
# change or a console line reaches them within it (people reading; nothing safety-related).
STREAMS_PERIOD_S = 0.1


def idle_period(rates: list[tuple[int, float]]) -> float:
    """The wait between two reads with nobody connected: for each ring (slots, publications per
    second seen), a quarter of the time it takes to fill, the shortest of them, within
    [IDLE_MIN_S, IDLE_PERIOD_S]."""
    period = IDLE_PERIOD_S
    for slots, rate in rates:
        if rate > 0:
            period = min(period, slots / rate / RING_MARGIN)
    return max(IDLE_MIN_S, period)


# With nobody taking monitor lines the output file is polled at the reader's first wake-up at
# least OUTPUT_IDLE_S apart: its idle batch, every 4 s with nobody connected (it was a timer of
# its own once a second: issue 30 item 4, session 14). The lines go to nobody then; the file
# keeps everything, and a client connecting lets the poll go at once (Supervisor._client_connected).
OUTPUT_IDLE_S = 2.0
OUTPUT_IDLE_LATEST_S = 6.0  # by its own timer, should the reader not wake (no shared memory yet)
OUTPUT_POLL_S = 0.1  # with one taking monitor lines: at the reader's first wake-up this long apart
# ... once the file has grown (an fstat at that wake-up, output_due); by its own timer this long
# after the last poll otherwise (the reader not waking, or a file that does not grow: the poll of
# an unchanged file was a task step 7 times a second with a dashboard, a tenth of the event
# loop's CPU with one: issue 30 item 4, session 16).
OUTPUT_POLL_LATEST_S = 1.0
READS_PER_POLL = 64  # 4 MiB of output per poll at most, then the event loop gets its turn


# The reader wakes this long after the sample due is expected: the loop's own wake-up jitter (tens
# of us on a quiet core, a millisecond or more on a busy one) mostly within it; a sample later than
# that is waited for on the doorbell.
TIMED_MARGIN_NS = 1_000_000


def next_publication(next_due_ns: int, last_t_ns: int, spacing_ns: int, period_ns: int) -> int:
    """When (the loop's clock, which is time.monotonic_ns() but in simulated time) the loop is
    expected to publish the telemetry sample due to be sent next, so that the reader wakes for
    it and not for the ones between, which it would only read and skip (a RELbot publishes 50 a
    second, dashboards get 30). `last_t_ns`: the last sample read; `spacing_ns`: the loop's
    spacing of publications (the last two samples'); the sample due is the first published at
    or after `next_due_ns`. 0 (not known: follow the doorbell) when the spacing is not known or
    the sample due would come later than one period."""
    if spacing_ns <= 0 or next_due_ns <= last_t_ns:
        return 0
    steps = -(-(next_due_ns - last_t_ns) // spacing_ns)  # publications until the one due
    expected = last_t_ns + steps * spacing_ns
    if expected - last_t_ns > max(period_ns, spacing_ns) * 2:
        return 0
    return expected


def message_due_at(
    next_due_ns: int, pending: int, per_message: int, last_t_ns: int, spacing_ns: int, period_ns: int
) -> int:
    """When the loop is expected to publish the sample that completes the next telemetry message
    (`pending` of its `per_message` samples already read): the (per_message - pending)-th sample
    due from `next_due_ns` on, one period apart. 0 (follow the doorbell) as next_publication."""
    need = max(1, per_message - pending)
    return next_publication(next_due_ns + (need - 1) * period_ns, last_t_ns, spacing_ns, period_ns * need)


def monitor_message_fields(run_id: int, lines: list[Any], lost: int) -> dict[str, Any]:
    """The wire fields of the MonitorMessage of the monitor ring's `lines` (channels' MonitorLine:
    cycle, t_ns, text), as the model dumps them (its fields' order, every field set)."""
    return {
        "run_id": run_id,
        "source": "monitor",
        "lines": [{"text": m.text, "cycle": m.cycle, "t_ns": m.t_ns} for m in lines],
        "lost": lost,
    }


def doorbell_thread(run: Run, loop: asyncio.AbstractEventLoop) -> None:
    """Blocks in the futex wait so the event loop never polls; wakes the reader task. Parked
    while the reader wakes itself (`run.reader_timed`); `run.idle_wake` unparks it."""
    ch = run.channels
    assert ch is not None
    seen = ch.doorbell
    while not run.thread_stop.is_set():
        if run.reader_timed:
            # Not in the futex: the loop then has no waiter to wake either (no system call).
            run.idle_wake.wait()
            run.idle_wake.clear()
            seen = ch.doorbell
            continue
        seen = ch.wait_doorbell(seen, DOORBELL_WAIT_MS)
        if run.reader_timed:  # the reader went on its own time meanwhile: no wake-up from here
            continue
        if not run.wake_pending:  # coalesce: one pending wake-up is enough
            run.wake_pending = True
            try:
                loop.call_soon_threadsafe(run.wake.set)
            except RuntimeError:  # event loop closed (shutdown)
                return


async def wait_wake(run: Run, loop: asyncio.AbstractEventLoop) -> None:
    """Until the reader's next wake-up: its own time (`run.wake_at_ns`, time.monotonic_ns()) or,
    with none, the doorbell thread's; `run.wake` set by anyone (a client connecting) ends it
    early either way."""
    if run.wake_at_ns and not run.wake.is_set():
        delay = (run.wake_at_ns - time.monotonic_ns()) / 1e9
        if delay > 0:
            timer = loop.call_later(delay, run.wake.set)
            try:
                await run.wake.wait()
            finally:
                timer.cancel()
    else:
        await run.wake.wait()
    run.wake.clear()
    run.wake_pending = False


def set_timed(run: Run, wake_at_ns: int) -> None:
    """The reader's next wake-up: at `wake_at_ns` by itself (the doorbell thread parked), or 0:
    on the doorbell (the thread unparked)."""
    run.wake_at_ns = wake_at_ns
    timed = wake_at_ns > 0
    if timed != run.reader_timed:
        run.reader_timed = timed
        if not timed:
            run.idle_wake.set()


async def read(run: Run, telemetry_hz: float, lifecycle: RunLifecycle, hub: Hub, per_message: int = 1) -> None:
    """The reader task: one batch per doorbell wake-up, until cancelled at the run's end.
    `per_message`: telemetry samples a message (Settings.telemetry_per_message)."""
    ch = run.channels
    assert ch is not None
    # Two cursors over the telemetry ring: the dashboards' (read at each wake-up while a client
    # takes telemetry, from the newest sample when one starts to) and the run observers' (every
    # sample, in bulk: see below).
    telemetry = ch.telemetry_reader()
    observed = ch.telemetry_reader()
    monitor = ch.monitor_reader()
    period_ns = int(1e9 / telemetry_hz) if telemetry_hz > 0 else 0
    per_message = max(1, per_message)
    # Samples due but not sent yet (their wire fields, oldest first): a message goes out when it
    # has per_message of them, or when its oldest has waited `hold_ns` on our clock (a loop that
    # stopped publishing, or publishes slower than telemetry_hz, still gets its samples shown).
    pending: list[dict[str, Any]] = []
    pending_since = 0
    hold_ns = per_message * (period_ns or DOORBELL_WAIT_MS * 1_000_000) + TIMED_MARGIN_NS
    next_due_ns = 0
    run_id = run.row.id
    t0 = 0  # the loop's first deadline (status t_start_ns): set once by cycle 1, read once here
    # The Ros2Xeno the loop has, read from its shared memory when its sequence moved: whoever
    # wrote it (this appliance, the ROS 2 bridge, a CLI), the Watch page shows the loop's.
    ros2xeno: dict[str, Any] = {}
    ros2xeno_seq = -1
    checked = False  # the first telemetry message is checked against its model (Hub.publish_fields)
    monitor_checked = False  # and the first monitor message
    last_t_ns = 0  # the last sample the dashboards' cursor read
    streaming = False  # the dashboards' cursor is following the ring
    # Simulated time: the loop's clock runs ahead of ours, so the reader follows the doorbell.
    virtual = ch.virtual_time
    last_read = observed_at = time.monotonic()
    observed_due = 0.0
    observed_rate = 0.0  # samples a second the observers' cursor last saw
    loop = asyncio.get_running_loop()
    live, live_at = False, -LIVE_RECHECK_S  # lifecycle.live(run), asked at live_at

    def send(samples: list[dict[str, Any]]) -> None:
        nonlocal checked
        # The wire fields as TelemetryMessage has them, built here rather than through the model
        # (the model cost more than the rest of the fan-out); the first is checked against the
        # model, the rest are made the same way.
        fields = {"run_id": run_id, "samples": samples, "ros2xeno": ros2xeno, "lost": telemetry.lost}
        if not checked:
            TelemetryMessage.model_validate(fields)
            checked = True
        run.telemetry_sent += len(samples)
        hub.publish_fields("telemetry", fields)

    while True:
        await wait_wake(run, loop)
        # The run's end (run_end.record) wakes us once more for the last batch: the observers
        # get what the loop published since the last bulk hand-over (up to IDLE_PERIOD_S of the
        # 3D view's recording), then the task returns before the mapping is let go.
        final = run.thread_stop.is_set()
        now = time.monotonic()
        output_due(run, now)
        since, last_read = now - last_read, now
        dashboards = hub.wants("telemetry")
        # The run observers (the 3D view's recording and model) take every sample, but need them
        # at once only while someone watches what they show (lifecycle.live): otherwise they get
        # them in bulk, a quarter of the ring's fill time apart (at most IDLE_PERIOD_S), which
        # costs one hand-over (in numpy: viz/scene.py) every few seconds instead of one per
        # wake-up (issue 30 item 4).
        # Whether they are watched is asked LIVE_RECHECK_S apart, not 30 times a second (the 3D
        # view's answer asks viser for its clients); a view opening gets its samples as they come
        # from a quarter of a second later.
        if now >= live_at + LIVE_RECHECK_S:
            live, live_at = lifecycle.live(run), now
        if not dashboards or now >= observed_due or live or final:
            batch = observed.read_batch()
            if batch:
                lifecycle.samples(run, batch)
            if now > observed_at:
                observed_rate = len(batch) / (now - observed_at)
            observed_at = now
            observed_due = now + idle_period([(observed.slots, observed_rate)])
        if final:
            run.output_poll.set()  # the console's poll reads the loop's last output now
            if pending and dashboards:  # the last samples due: sent as the run ends
                send(pending)
            return
        # Dashboards' streams: built only when a client (or a hub listener) takes them; a client
        # that connects gets new samples, not a backlog (the cursor starts at the newest).
        if dashboards and not streaming:
            telemetry.skip()
        streaming = dashboards
        if not dashboards:
            pending.clear()
        samples = telemetry.read_batch() if dashboards else None
        sent_state = -1  # the loop's state in the last sample sent in this batch
        if samples:
            if not t0:
                with contextlib.suppress(StatusBusy):  # mid-write: the next batch
                    t0 = ch.status().t_start_ns
            seq = ch.ros2xeno_seq
            if seq != ros2xeno_seq:
                got = ch.read_ros2xeno()  # None: a write in progress, keep the last and ask again
                if got is not None:
                    ros2xeno, ros2xeno_seq = got, seq
            ts = samples.t_ns
            for i, t_ns in enumerate(ts):
                # Credit-based decimation: the average rate is telemetry_hz exactly even when the
                # loop's own rate is not a multiple of it (100 Hz -> 30 Hz sends 3 of every 10).
                if period_ns:
                    if t_ns < next_due_ns:
                        continue
                    next_due_ns = max(next_due_ns + period_ns, t_ns - period_ns)
                sample = samples[i]
                sent_state = sample.state
                if not pending:
                    pending_since = time.monotonic_ns()
                # TelemetrySample's wire fields, in its order.
                pending.append(
                    {
                        "cycle": sample.cycle,
                        "t_ns": t_ns,
                        "t": (t_ns - t0) / 1e9 if t0 else t_ns / 1e9,
                        "state": sample.state,
                        "enc": sample.enc,
                        "din": sample.din,
                        "pwm": sample.pwm,
                        "dout": sample.dout,
                        "xeno2ros": sample.xeno2ros,
                        "ros2xeno_t_sent_ns": sample.ros2xeno_t_sent_ns,
                    }
                )
                if len(pending) >= per_message:
                    send(pending)
                    pending = []
            prev = ts[-2] if len(ts) > 1 else last_t_ns
            spacing = ts[-1] - prev if prev else 0
            last_t_ns = ts[-1]
        elif not dashboards:
            last_t_ns = spacing = 0
        else:
            spacing = 0  # nothing new: the sample due is late, the doorbell brings it
        if pending and time.monotonic_ns() - pending_since > hold_ns:
            send(pending)  # the loop publishes slower than the message needs, or stopped
            pending = []
        lines = monitor.read()
        wanted = dashboards or hub.wants("monitor") or hub.wants("state")
        if not dashboards and since > 0:
            run.idle_period = idle_period([(observed.slots, observed_rate), (monitor.slots, len(lines) / since)])
        if not wanted and not live:
            set_timed(run, time.monotonic_ns() + int(until_aligned(run.idle_period) * 1e9))
        elif not dashboards:
            # Clients of the state or monitor lines, or a 3D view watched with no dashboard (its
            # scene then follows the samples 10 times a second, not at each idle batch).
            set_timed(run, time.monotonic_ns() + int(min(STREAMS_PERIOD_S, run.idle_period) * 1e9))
        else:
            expected = (
                0
                if virtual or not period_ns
                else message_due_at(next_due_ns, len(pending), per_message, last_t_ns, spacing, period_ns)
            )
            wake_at = expected + TIMED_MARGIN_NS if expected else 0
            set_timed(run, wake_at if wake_at > time.monotonic_ns() else 0)
        if lines and hub.wants("monitor"):
            # As telemetry: the wire fields built here (monitor_message_fields: MonitorMessage's),
            # the first message checked against the model; a model per message, each line one
            # too, was a twentieth of the appliance's Python with a dashboard (issue 30 item 4).
            monitor_fields = monitor_message_fields(run_id, lines, monitor.lost)
            if not monitor_checked:
                MonitorMessage.model_validate(monitor_fields)
                monitor_checked = True
            hub.publish_fields("monitor", monitor_fields)
        # The state check copies the 33 KB status block; the samples carry the loop's state, so
        # while the one sent says what was last published, it is made STATUS_REFRESH_S apart,
        # not at every batch (a rejection or an error without a state change is seen within it).
        key = run.last_state_key
        if sent_state < 0 or key is None or sent_state != key[0] or now - run.last_status_at >= STATUS_REFRESH_S:
            refresh_state(run, hub, per_batch=True)


async def pipe_output(run: Run, hub: Hub) -> None:
    """Follow the loop's stdout/stderr file into the monitor console. Polled every 100 ms while a
    dashboard takes monitor lines (at a wake-up of the reader's: `with_reader`), at the reader's
    idle batch otherwise (OUTPUT_IDLE_S; the file keeps everything; a
    console opened later shows lines from then on): this is for people reading, nothing
    safety-related waits on it. What the guest printed is
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
        run.output_fd = f.fileno()  # the reader looks whether it grew (output_due)
        try:
            await _follow_output(run, hub, f, cutter, publish, say_skipped)
        finally:
            run.output_fd = -1


async def _follow_output(
    run: Run,
    hub: Hub,
    f: BinaryIO,
    cutter: OutputLines,
    publish: Callable[[list[str]], None],
    say_skipped: Callable[[], None],
) -> None:
    """pipe_output's polls of the open file `f`, until the run has ended and it is read whole."""
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
        run.output_read = f.tell()
        caught_up = len(chunk) < 65536
        if caught_up and not alive:
            cutter.flush(lines)
        publish(lines)
        say_skipped()
        if caught_up and not alive:
            return
        if not caught_up:
            await asyncio.sleep(0.01)
        elif hub.wants("monitor"):
            await with_reader(run, OUTPUT_POLL_S, OUTPUT_POLL_LATEST_S)
        else:
            await with_reader(run, OUTPUT_IDLE_S, OUTPUT_IDLE_LATEST_S)


def output_due(run: Run, now: float) -> None:
    """At each of the reader's wake-ups (time.monotonic() `now`): the console's output poll
    waiting in `with_reader` is let go once it is due and the file has grown since its last read
    (or shrunk: a loop may truncate it), to run in this same wake-up."""
    if run.output_due and now >= run.output_due:
        if run.output_fd >= 0:
            try:
                if os.fstat(run.output_fd).st_size == run.output_read:
                    return  # nothing new: no step of the console's task for it
            except OSError:
                pass  # the poll says what is wrong
        run.output_poll.set()


async def with_reader(run: Run, period_s: float, latest_s: float = 0.0) -> None:
    """Until about `period_s` from now, at one of the reader's own wake-ups (it sets
    `run.output_poll` at its first batch past `run.output_due`): the console's poll then costs
    no wake-up of its own (10 a second, a sixth of the appliance's with one dashboard, issue 30
    item 4). By a timer of its own after `latest_s` (default: half a period later), should the
    reader not wake. A client connecting, and the run's end, let it go at once."""
    loop = asyncio.get_running_loop()
    run.output_poll.clear()
    run.output_due = time.monotonic() + period_s
    timer = loop.call_later(latest_s or period_s * 1.5, run.output_poll.set)
    try:
        await run.output_poll.wait()
    finally:
        timer.cancel()
        run.output_due = 0.0


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
