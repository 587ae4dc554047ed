"""Host logging as a run observer (server/runs/lifecycle.py): the appliance writes each run's log files.

When the run's shared memory is open, the host writer (logs/live.py) starts draining the loop's
log ring into the run folder (and the live rerun stream, and the timing writer when the run logs
its per-cycle timing). When the loop process is gone (on_exited), the rest of the ring is drained
(even after a crash) and the counts go into the run record, before the supervisor writes how the
run ended: whoever sees the run ended sees its final counts.
"""

from __future__ import annotations

import asyncio
import logging
import os
from collections.abc import Callable
from typing import TYPE_CHECKING

from ...logs import live
from ..ws.messages import AlarmMessage, MonitorLine, MonitorMessage, ServerMessage
from .lifecycle import RunObserver
from .store import RunStore

if TYPE_CHECKING:
    from .run import Run

log = logging.getLogger("xrflab.logs")


class HostLogging(RunObserver):
    name = "host logging"

    def __init__(self, publish: Callable[[ServerMessage], None], store: RunStore) -> None:
        self._publish = publish
        self._store = store

    def on_started(self, run: Run) -> None:
        ch = run.channels
        if ch is None:
            return
        row = run.row
        publish, store = self._publish, self._store
        loop = asyncio.get_running_loop()

        def console(text: str) -> None:  # called from the writer thread
            try:
                loop.call_soon_threadsafe(
                    publish, MonitorMessage(run_id=row.id, source="appliance", lines=[MonitorLine(text=text)])
                )
            except RuntimeError:  # event loop closed (shutdown)
                pass

        def alarm(message: str) -> None:  # called from the writer thread
            def on_loop() -> None:
                publish(AlarmMessage(kind="log", run_id=row.id, message=message))
                publish(MonitorMessage(run_id=row.id, source="appliance", lines=[MonitorLine(text=message)]))
                try:
                    store.update(row.id, log_note=message)
                except Exception:  # the database may sit on the same full disk
                    log.exception("run %s: cannot record the log note", row.id)

            try:
                loop.call_soon_threadsafe(on_loop)
            except RuntimeError:
                pass

        identity = {"project": row.build, "build": row.build, "run": str(row.id)}
        run.logging = live.start(
            ch,
            row.id,
            run.run_dir,
            identity,
            row.owner,
            alarm,
            live=os.environ.get("XRF_LIVE_RERUN", "1") != "0",
            log_timing=run.log_timing,
            on_note=console,
            on_corrupt=run.report_corrupt,
        )

    async def on_exited(self, run: Run) -> None:
        """The rest of the log ring (the mapping is still ours), then the counts."""
        rl = run.logging
        if rl is None:
            return
        stats = await asyncio.to_thread(live.finish, rl)
        try:
            run.row = self._store.update(
                run.row.id, log_records=stats.records, log_lost=stats.lost + stats.unwritten, log_note=stats.failed
            )
        except Exception:
            log.exception("run %s: cannot record the log counts", run.row.id)
