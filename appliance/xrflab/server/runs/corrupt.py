"""A run whose loop broke the rules of its shared memory: stopped, with an alarm of its own.

Every reader of the segment (channels/, logs/log_channel.py) bounds what the loop wrote and
raises ``ChannelsCorrupt`` where a geometry, head, tail, layout or schema is not one the runtime
writes (docs/developers/security.md, "The shared segment"). Whoever sees it -- the reader task,
the host log writer's thread, a command, the opening of the segment -- calls
``run.report_corrupt`` (from any thread); the run is then stopped like the disk guard stops one:
its record keeps what it had (the log up to the violation included) and says why, the alarm
``corrupt_channel`` goes to the dashboards, the loop gets SIGINT, SIGTERM, SIGKILL
(run_control.terminate), and the run ends with ``end_reason`` ``corrupt_channel``. The
appliance and every other page go on: nothing of the run's segment is trusted any more.
"""

from __future__ import annotations

import asyncio
import logging

from ...channels import ChannelsCorrupt
from ..settings import Settings
from ..ws.hub import Hub
from ..ws.messages import AlarmMessage
from .control import terminate
from .run import Run
from .store import RunStore

log = logging.getLogger("xrflab.supervisor")


def watch(run: Run, settings: Settings, store: RunStore, hub: Hub) -> None:
    """Give `run` its ``report_corrupt`` (callable from any thread). Call in the event loop."""
    loop = asyncio.get_running_loop()

    def report(exc: ChannelsCorrupt) -> None:
        try:
            loop.call_soon_threadsafe(stop, run, str(exc), settings, store, hub)
        except RuntimeError:  # event loop closed (shutdown)
            pass

    run.report_corrupt = report


def stop(run: Run, what: str, settings: Settings, store: RunStore, hub: Hub) -> None:
    """In the event loop: record why, raise the alarm, stop the run (once)."""
    if run.corrupt or run.ended.is_set():
        return
    run.corrupt = what
    message = f"the controller broke the rules of its shared memory: {what}; run stopped"
    log.warning("run %s: %s", run.row.id, message)
    run.row = store.update(run.row.id, message=message)
    hub.publish(AlarmMessage(kind="corrupt_channel", end_reason="corrupt_channel", run_id=run.row.id, message=message))
    run.stop_requested = True
    run.end_reason = run.end_reason or "corrupt_channel"
    # A task of its own: the reader that saw it is cancelled at the run's end (run_end.MAPPING_TASKS).
    run.tasks.append(asyncio.create_task(terminate(run, settings), name=f"run{run.row.id}-corrupt"))
