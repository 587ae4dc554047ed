"""The supervisor: builds, starts, watches and stops loop processes, one run at a time.

A run is one loop process plus its shared memory (/dev/shm/<name>, a fresh name per run). The
supervisor owns that memory: it opens it with ``Channels``, writes the host heartbeat the loop
checks (XRF_HOST_TIMEOUT_MS: the loop pauses itself if we die), reads state/telemetry/monitor
when the loop rings the doorbell, and unlinks the object when the run is over.

This class is the façade the routes use (start, command, setpoint, stop, what to show); each job
is a module of its own that takes the `Run` it works on:

- server/runs/catalog.py: the builds a run starts from (bundled examples built on first use, uploads);
- server/runs/launch.py: the loop's environment, its sandbox, mapping its shared memory;
- server/runs/watch.py: the safety watcher, the heartbeats, the limits guard, the exit (safe outputs first);
- server/runs/reader.py: telemetry and monitor lines on the doorbell, the loop's printed output;
- server/runs/timing.py: the once-a-second timing message and deadline-miss alarm;
- server/runs/control.py: commands, setpoints, stopping in order;
- server/runs/end.py: how a run ended, in its record, then the browsers;
- server/runs/corrupt.py: a run whose loop broke the rules of its shared memory, stopped with its alarm;
- server/runs/orphans.py: runs a dead appliance left live, closed at start-up;
- server/runs/announce.py: the `run` and `state` messages;
- server/runs/run.py: the `Run` itself, `SupervisorError`, `remove_shm`.

What reacts to a run's start, samples, exit and end beyond this (host logging, the 3D view, the
lease, the ROS bridge) is a run observer (server/runs/lifecycle.py), told in order.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
from pathlib import Path
from typing import Any

from ... import channels as chmod
from ... import plants
from ..settings import Settings
from ..ws.hub import Hub
from ..ws.messages import RunMessage, ServerMessage, StateMessage
from . import control as run_control
from . import corrupt as run_corrupt
from . import end as run_end
from . import launch, orphans
from . import limits as run_limits
from . import reader as run_reader
from . import watch as run_watch
from .announce import RunEvent, refresh_state, run_message, schema_fields, state_message
from .catalog import BuildCatalog, BuildEntry
from .guest_spawn import GuestSpawner
from .lifecycle import RunLifecycle
from .run import Run, SupervisorError, remove_shm
from .store import RunRow, RunStore
from .timing import timing

# The names other modules and the docs know the supervisor's parts by.
__all__ = ["BuildCatalog", "BuildEntry", "Run", "Supervisor", "SupervisorError", "remove_shm", "schema_fields"]

log = logging.getLogger("xrflab.supervisor")


class Supervisor:
    def __init__(self, settings: Settings, hub: Hub, store: RunStore) -> None:
        self.settings = settings
        self.hub = hub
        self.store = store
        self.catalog = BuildCatalog(settings, hub.publish)
        self.guests = GuestSpawner(settings)
        self.current: Run | None = None
        self.last_row: RunRow | None = None
        # Held while a run starts, and by anything else that needs the bench to itself (the
        # FPGA self-check holds it for its whole duration, so no run can start meanwhile).
        self.bench_lock = asyncio.Lock()
        # What reacts to a run starting, its telemetry and its end (host logging, the 3D view,
        # the lease, the ROS bridge): registered by the app at start-up, told in order.
        self.lifecycle = RunLifecycle()
        # Runs a previous appliance process left live (it was killed or died): recover_orphans()
        # closes them once the event loop runs.
        self._orphans = list(store.orphans)
        hub.on_client.append(self._client_connected)
        self._loop: asyncio.AbstractEventLoop | None = None  # the event loop the runs' tasks run in

    def _client_connected(self) -> None:
        """A dashboard connected: the current run's reader reads now and follows the dashboards'
        rate from then on, not from its next idle wake-up (server/runs/reader.py); the console's
        output poll, which waits for the reader's idle batch while nobody takes monitor lines,
        goes now too (the client's first lines within a poll period, not seconds later)."""
        run = self.current
        if run is not None:
            run.wake.set()
            run.output_poll.set()

    def wake_reader(self) -> None:
        """A run observer started to be watched (the 3D view: a viewer, a state poll): the current
        run's reader reads now and hands the observers each batch from then on, not at its next
        idle wake-up, up to IDLE_PERIOD_S later (server/runs/reader.py). From any thread."""
        run, loop = self.current, self._loop
        if run is None or loop is None or run.ended.is_set():
            return
        with contextlib.suppress(RuntimeError):  # the event loop closed (shutdown)
            loop.call_soon_threadsafe(run.wake.set)

    async def recover_orphans(self) -> None:
        """Close the runs a dead appliance left behind (server/runs/orphans.py). Each orphan keeps the bench
        lock until it is closed."""
        rows, self._orphans = self._orphans, []
        for row in rows:
            async with self.bench_lock:
                try:
                    self.last_row = await orphans.recover(row, self.settings, self.store)
                    await self.lifecycle.ended(self.last_row, None)
                    orphans.announce(self.last_row, self.hub)
                except Exception:  # one bad record must not keep the appliance from serving
                    log.exception("run %s: recovering the orphaned run failed", row.id)
                    orphans.abandon(row)
        # What a killed appliance left of its runs' cgroups and file systems (the run's files kept).
        async with self.bench_lock:
            live = {self.current.run_dir} if self.current is not None and not self.current.ended.is_set() else set()
            try:
                for note in await asyncio.to_thread(run_limits.sweep, self.settings, live):
                    log.warning("left by an earlier appliance: %s", note)
            except Exception:
                log.exception("cleaning up what an earlier appliance left failed")

    # -- queries ------------------------------------------------------------------------------

    def bench(self) -> dict[str, Any]:
        real = self.settings.bench_is_real()
        return {
            "mode": "real" if real else "sim",
            "sim": "" if real else self.settings.sim,
            "profile": "ico-board over EVL spidev" if real else f"simulated ico board + {self.settings.sim} plant",
            "evl": Path("/dev/evl").exists(),
            "spidev": Path(self.settings.spi_device).exists(),
            "telemetry_hz": self.settings.telemetry_hz,
            "telemetry_per_message": self.settings.telemetry_per_message,
        }

    def run_message(self, run: Run | None = None, event: RunEvent = "current") -> RunMessage:
        return run_message(run or self.current, self.last_row, event)

    def state_message(self, run: Run | None = None) -> StateMessage:
        return state_message(run or self.current)

    def state_payload(self) -> dict[str, Any]:
        """The current `state` message's fields as a dict, for code that is not a browser (the
        room's bench facts)."""
        return self.state_message().model_dump(exclude_unset=True, exclude={"type"})

    def snapshot(self) -> list[ServerMessage]:
        """What a new WebSocket client receives first (hub.add_snapshot): the run, its state."""
        return [self.run_message(), self.state_message()]

    # -- starting -----------------------------------------------------------------------------

    async def start_run(
        self,
        build: str,
        sim: str | None = None,
        max_cycles: int | None = None,
        owner: str = "",
        log_timing: bool = False,
    ) -> RunRow:
        """`owner`: username of who starts it (auth.owns() decides who may see the run).
        `log_timing`: the loop logs every cycle's stage timing (cycle_timing.xrf in the run)."""
        async with self.bench_lock:
            if self.current is not None and not self.current.ended.is_set():
                raise SupervisorError(f"run {self.current.row.id} is still active; stop it first")
            # A real bench whose boards cannot all be reached (an SPI device per board) is not
            # started (nor anything built for it).
            refusal = run_watch.bench_refusal(self.settings)
            if refusal:
                raise SupervisorError(refusal, 409)
            entry = await self.catalog.ensure_built(build)
            assert entry.executable is not None
            plant = sim or entry.sim
            if plant not in plants.names():
                raise SupervisorError(f"unknown simulated plant {plant!r}; have: {', '.join(plants.names())}", 422)
            row = self.store.create(build, plant, "", "")
            if owner:
                row = self.store.update(row.id, owner=owner)
            try:
                run = await launch.spawn(
                    row, entry, plant, max_cycles, log_timing, self.settings, self.guests, self.store
                )
            except launch.StartRefused as refused:
                self.last_row = refused.row
                launch.announce_refused(refused, self.hub)
                raise
            self.current = run
            run_corrupt.watch(run, self.settings, self.store, self.hub)
            launch.announce_unconfined(run, self.hub)
            run.tasks.append(asyncio.create_task(self._watch_exit(run), name=f"run{row.id}-exit"))
            if run.limits is not None:  # from the start: a controller may fill its disk before its shm exists
                guard = run_watch.limits_guard(run, run.limits, self.settings, self.store, self.hub)
                run.tasks.append(asyncio.create_task(guard, name=f"run{row.id}-limits"))
            run.tasks.append(asyncio.create_task(run_reader.pipe_output(run, self.hub), name=f"run{row.id}-output"))

            try:
                opened = await launch.open_channels(run, self.settings, self.store)
                if opened:
                    # Started even when the loop has ended meanwhile (its end waits for `settled`
                    # and then drains the log as for any run); only its watcher is not.
                    info = run.channels.info if run.channels else {}
                    if run.alive:
                        run_watch.start_watcher(run, self.settings)
                    run.row = self.store.update(
                        row.id, status="running", program=info.get("program", ""), cycle_freq=info.get("cycle_freq", 0)
                    )
                    self.lifecycle.started(run)  # host logging first: the log writer starts draining now
                    self._start_tasks(run)
                    refresh_state(run, self.hub)
            finally:
                run.settled.set()
            if not opened:
                await run.ended.wait()
                assert self.last_row is not None
                return self.last_row
            self.hub.publish(self.run_message(run, "started"))
            return run.row

    def _start_tasks(self, run: Run) -> None:
        """The tasks and the doorbell thread of a run whose shared memory is open. The names'
        ends say which stop before the mapping is let go (run_end.MAPPING_TASKS)."""
        rid, hub, settings = run.row.id, self.hub, self.settings
        self._loop = asyncio.get_running_loop()
        run.tasks.append(asyncio.create_task(run_watch.heartbeat(run, settings), name=f"run{rid}-heartbeat"))
        # "_reader"/"_timing": the names the console has always given them when they fail.
        reader = run_reader.guarded(
            "_reader",
            lambda: run_reader.read(run, settings.telemetry_hz, self.lifecycle, hub, settings.telemetry_per_message),
            run,
            hub,
        )
        run.tasks.append(asyncio.create_task(reader, name=f"run{rid}-reader"))
        timer = run_reader.guarded("_timing", lambda: timing(run, settings.timing_period_s, hub), run, hub)
        run.tasks.append(asyncio.create_task(timer, name=f"run{rid}-timing"))
        run.thread = threading.Thread(
            target=run_reader.doorbell_thread,
            args=(run, asyncio.get_running_loop()),
            name=f"xrf-doorbell-{rid}",
            daemon=True,
        )
        run.thread.start()

    async def _watch_exit(self, run: Run) -> None:
        """The run's last task: its exit (outputs safe), its record, then the browsers."""
        returncode = await run_watch.wait_for_exit(run, self.settings)  # outputs safe first
        # A loop that ended while its start was under way (a short run on a loaded machine): its
        # end after the start, or the start marked the ended run running and started its logging
        # and tasks after their end (CI, session 13: a 10-cycle run stayed "running" for good).
        await run.settled.wait()
        ending = await run_end.record(run, returncode, self.settings, self.store, self.lifecycle)
        self.last_row = run.row
        run_end.announce(run, ending, self.hub)

    # -- controlling --------------------------------------------------------------------------

    async def command(self, cmd: str | int) -> chmod.CommandResult:
        """Queue a command, wait until the loop handled it, publish the state at once."""
        number = chmod.command_number(cmd)  # ValueError for unknown names
        return await run_control.command(run_control.active(self.current), number, self.hub)

    def setpoint(self, fields: dict[str, Any]) -> dict[str, Any]:
        """Merge into the run's Ros2Xeno (latest wins, so the whole message is written)."""
        return run_control.setpoint(run_control.active(self.current), fields)

    async def stop_current(self, by: str = "") -> RunRow:
        """Stop the active run in order. `by`: who asked (a username): someone other than the
        run's owner (an educator, a self-check) is named in the run's end."""
        run = self.current
        if run is None or run.ended.is_set():
            raise SupervisorError("no run is active")
        await run_control.stop(run, by, self.settings, self.store)
        return run.row

    async def shutdown(self) -> None:
        """Appliance stopping: end the run in order so the loop leaves its outputs off."""
        if self.current is not None and not self.current.ended.is_set():
            self.current.end_reason = self.current.end_reason or "shutdown"
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self.stop_current(), 15)
