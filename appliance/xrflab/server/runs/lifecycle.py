"""The run life cycle: one ordered list of observers the supervisor tells that a run started,
that the reader took telemetry, that its loop process is gone, and that the run ended.

Before this module, what reacted to a run's start or end was wired five ways (direct calls into
logs/live, a telemetry observer list, the lease and the ROS bridge matching the JSON sent to
browsers): renaming a dashboard field could silently stop the lease from hearing a run end. Now
every reaction is a `RunObserver` registered once, in the app's lifespan (app.py), in this
order, which is the order they are told:

1. host logging (server/runs/log_writer.py): starts the log writer when the run's shared memory is
   open; once the loop process is gone (``on_exited``) drains the rest of the log ring and adds
   the counts to the run record, before the record says the run ended: whoever sees it ended
   (a browser polling the run, every later observer, the "run ended" message) sees the counts;
2. the 3D view (viz/scene.py): follows the telemetry, closes its recording at the end;
3. the bench lease (server/security/lease.py): the end counts as the holder's activity;
4. live tuning (params/service.py): the run's parameter table at its start, saved parameters set;
5. the ROS 2 bridge (server/runs/ros_bridge.py): one bridge per run, started and stopped with it.

The supervisor announces the run to the browsers (the hub's ``run`` message) itself, after
every observer has been told: the message is for people, not a signal for code.

How to add one: docs/developers/adding-a-run-observer.md.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .run import Run
    from .store import RunRow

log = logging.getLogger("xrflab.lifecycle")


class RunObserver:
    """Something that reacts to runs. Override what you need; the defaults do nothing.

    All are called in the event loop and must not block it (start threads or tasks for slow
    work; ``on_exited`` and ``on_ended`` may await it)."""

    name = "observer"

    def on_started(self, run: Run) -> None:
        """The run's shared memory is open (``run.channels`` is set) and its record says
        ``running``; the reader has not taken a sample yet."""

    def on_samples(self, run: Run, samples: Sequence[Any]) -> None:
        """A batch of telemetry samples (channels.Telemetry; a channels.TelemetryBatch, whose
        `t_ns`, `cycle`, `enc`, `din` are columns already), every one of them, in order (before
        the dashboards' decimation). In bulk, up to a second's worth at a time, unless `live`
        says the observer shows them now. Must be quick: it runs in the event loop."""

    def live(self, run: Run) -> bool:
        """Whether this observer needs each sample as soon as it is read (someone watches what
        it shows); otherwise the reader hands them over in bulk (server/runs/reader.py)."""
        return False

    async def on_exited(self, run: Run) -> None:
        """The loop process is gone (the outputs are safe) and the run's shared memory is still
        mapped, but the record does not say how the run ended yet: for what the final record
        must include (host logging's counts). Until every observer returns, the run's record
        still says ``running``."""

    async def on_ended(self, row: RunRow, run: Run | None) -> None:
        """The run is over and its record is final: ``row.end_reason`` says how it ended
        (runs.END_REASONS). ``run`` is the live run object; None for a run a previous appliance
        process left behind (recovered at start-up: there is only its record)."""


class RunLifecycle:
    """The ordered list. An observer that raises is logged and the next one is told anyway; one
    whose ``on_samples`` raises is not given samples any more (a broken 3D view must not log a
    traceback 50 times a second), but still hears the run's start and end."""

    def __init__(self) -> None:
        self._observers: list[RunObserver] = []
        self._no_samples: set[int] = set()  # id() of observers whose on_samples failed

    def register(self, observer: RunObserver) -> None:
        """Add an observer at the end of the list (registration order is call order)."""
        if observer in self._observers:
            raise ValueError(f"run observer {observer.name} is registered already")
        self._observers.append(observer)

    def unregister(self, observer: RunObserver) -> None:
        if observer in self._observers:
            self._observers.remove(observer)
        self._no_samples.discard(id(observer))

    @property
    def observers(self) -> tuple[RunObserver, ...]:
        return tuple(self._observers)

    def started(self, run: Run) -> None:
        for obs in tuple(self._observers):
            try:
                obs.on_started(run)
            except Exception:
                log.exception("run %s: observer %s failed on start", run.row.id, obs.name)

    def samples(self, run: Run, samples: Sequence[Any]) -> None:
        for obs in tuple(self._observers):
            if id(obs) in self._no_samples:
                continue
            try:
                obs.on_samples(run, samples)
            except Exception:
                log.exception("run %s: observer %s failed on samples; it gets none any more", run.row.id, obs.name)
                self._no_samples.add(id(obs))

    def live(self, run: Run) -> bool:
        """Whether an observer wants the samples as they come (RunObserver.live)."""
        for obs in self._observers:
            if id(obs) in self._no_samples:
                continue
            try:
                if obs.live(run):
                    return True
            except Exception:
                log.exception("run %s: observer %s failed on live", run.row.id, obs.name)
                self._no_samples.add(id(obs))
        return False

    async def exited(self, run: Run) -> None:
        for obs in tuple(self._observers):
            try:
                await obs.on_exited(run)
            except Exception:
                log.exception("run %s: observer %s failed on exit", run.row.id, obs.name)

    async def ended(self, row: RunRow, run: Run | None) -> None:
        for obs in tuple(self._observers):
            if run is not None:
                row = run.row  # an observer before this one may have added to the record
            try:
                await obs.on_ended(row, run)
            except Exception:
                log.exception("run %s: observer %s failed on end", row.id, obs.name)
