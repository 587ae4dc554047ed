"""A run's logging on the appliance, as one unit: what starts with a run and ends with it.

A run that logs gets, from ``start`` (called by the host-logging run observer,
server/runs/log_writer.py) to ``finish`` (once its loop process is gone):

- the **host log writer** of its logger's ring (``host_writer.py``: ring → file segments, the
  per-second timing series of ``timing_series.py``);
- a second writer for the per-cycle timing records when the run logs them (XRF_LOG_TIMING=1);
- the **live rerun stream** (``rerun_live.py``) on the run's own rerun proxy
  (``rerun_servers.py``), unless switched off (XRF_LIVE_RERUN=0) or unavailable: it is
  connected on a thread of its own and the writer does not wait for it.

``loop_env`` is the loop's side of it: the environment that makes the loop hand its log
records to the appliance. See docs/logging/appliance.md.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from .host_writer import HostLogWriter, WriterStats
from .rerun_live import LiveRerun
from .rerun_servers import LiveProxy

if TYPE_CHECKING:
    from ..channels import Channels, ChannelsCorrupt

log = logging.getLogger("xrflab.logs.live")


@dataclass
class RunLogging:
    writer: HostLogWriter
    live: LiveRerun | None
    starting: threading.Thread | None = None
    proxy: LiveProxy | None = None  # the run's live proxy (told when the run has ended: finish)
    timing: HostLogWriter | None = None  # per-cycle timing records (XRF_LOG_TIMING=1)


def start(
    ch: Channels,
    run_id: int,
    run_dir: Path,
    identity: dict[str, str],
    owner: str,
    on_alarm: Callable[[str], None],
    live: bool = True,
    log_timing: bool = False,
    on_note: Callable[[str], None] | None = None,
    on_corrupt: Callable[[ChannelsCorrupt], None] | None = None,
) -> RunLogging:
    """Start the host writer (and the live rerun stream unless disabled or unavailable; and the
    timing writer when the loop logs its per-cycle timing). `on_note`: a line for the run's
    console (where a log file went). `on_corrupt`: the loop broke a log channel (the writer of it
    has stopped; the supervisor stops the run)."""
    # The timing series' samples are taken by the supervisor's once-a-second timing task
    # (server/runs/timing.py, take_timing): the writer's thread then wakes only for its drains.
    writer = HostLogWriter(
        ch, identity, run_dir, on_alarm=on_alarm, on_note=on_note, on_corrupt=on_corrupt, timing_in_thread=False
    )
    writer.start()
    rl = RunLogging(writer, None)
    if log_timing:
        rl.timing = HostLogWriter(
            ch,
            identity,
            run_dir,
            on_alarm=on_alarm,
            timing=False,
            source="cycle_timing",
            on_note=on_note,
            on_corrupt=on_corrupt,
        )
        rl.timing.start()
    if live and os.environ.get("XRF_LIVE_RERUN", "1") != "0":
        # rerun's import and servers take a moment on the first run: not on the event loop,
        # and the writer does not wait for them (records before the stream is up are not sent live).
        def connect() -> None:
            try:
                rl.proxy = LiveProxy.open_for_run(run_id, owner)
                rl.live = LiveRerun(rl.proxy, ch, run_id, wake_writer=writer.wake)
                writer.set_on_records(rl.live.feed, fast=rl.live.watched)
            except Exception:
                log.exception("live rerun unavailable")

        rl.starting = threading.Thread(target=connect, name=f"xrf-rerun-start-{run_id}", daemon=True)
        rl.starting.start()
    return rl


def release_freed_memory() -> None:
    """glibc's malloc_trim(0): the free pages inside the malloc arenas and the top of the heap
    given back to the system. A run's logging and what came with it (the live stream, the
    downloads and dashboards of the round before) free memory in pieces the allocator keeps;
    once a run, it costs a walk of the arenas (~1 ms). Nothing where there is no glibc."""
    import ctypes

    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None).malloc_trim(0)


def finish(rl: RunLogging) -> WriterStats:
    if rl.timing is not None:
        rl.timing.finish()
    stats = rl.writer.finish()
    release_freed_memory()  # the writer's buffers are gone (bench/README.md, "memory")
    if rl.starting is not None:
        rl.starting.join(30.0)
    # The proxy's process is stopped once the run has ended and nobody watches (rerun_servers.py
    # LiveProxy.run_ended), after the recording's last batch reached it.
    if rl.live is not None:
        rl.live.close(then=rl.proxy.run_ended if rl.proxy is not None else None)
    elif rl.proxy is not None:
        rl.proxy.run_ended()
    return stats


__all__ = ["HostLogWriter", "RunLogging", "WriterStats", "finish", "loop_env", "start"]


# ---- the loop's environment (appliance/xrflab/server/runs/launch.py) ------------------------------
# Starting and finishing a run's logging: server/runs/log_writer.py, a run observer (server/runs/lifecycle.py).


def loop_env(run_id: int, build: str, log_timing: bool = False) -> dict[str, str]:
    """Environment for a run's loop process: the appliance writes the log files (host writer)."""
    env = {"XRF_LOG_WRITER": "host", "XRF_RUN_ID": str(run_id), "XRF_BUILD_ID": build, "XRF_PROJECT": build}
    if log_timing:
        env["XRF_LOG_TIMING"] = "1"
    return env
