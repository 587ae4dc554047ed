"""One run: a loop process, its shared memory, the tasks that watch it and what they learnt.

A `Run` is the live object the supervisor's parts share (launch, watch, reader, timing,
control, end); its record in the database is `run.row` (runs.RunRow), kept up to date as the run
goes. Everything here is data, no behaviour beyond `alive`: each part of the supervisor is a
module of its own that takes the run it works on.

The run's shared memory belongs to the appliance, not to the loop: the appliance makes it (a
sealed memfd, `shm_fd`: the loop cannot resize it under the appliance's mapping), the loop never
unlinks it (a crash could not), and the appliance needs the final state after the loop's end.
`remove_shm` lets go of its name once the run is recorded (docs/developers/architecture.md,
"Whose segment").
"""

from __future__ import annotations

import asyncio
import contextlib
import subprocess
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ... import channels as chmod
from ... import guest
from ...channels import Channels, ChannelsCorrupt, segment
from ...logs import live as loglive
from ...runfolder import remove_folder
from .children import Child
from .errors import SupervisorError as SupervisorError  # its home is errors.py; launch and control import it here
from .guest_spawn import GuestReport
from .limits import RunLimits
from .safety import SafetyWatcher, WatchResult
from .store import RunRow

if TYPE_CHECKING:
    from .catalog import BuildEntry


# The run segment's name below /dev/shm: <the loop's /dev/shm folder> + this, a symlink to the
# appliance's descriptor of it (launch.segment_link); defined where the segment is opened.
SEGMENT_LINK_SUFFIX = segment.SEGMENT_LINK_SUFFIX


@dataclass
class Run:
    row: RunRow
    proc: Child  # the run sandbox's launcher (its exit mirrors the controller's)
    shm: str
    run_dir: Path
    build: BuildEntry
    shm_fd: int = -1  # the run's segment (a sealed memfd), ours until remove_shm; -1: by name only
    channels: Channels | None = None
    stop_requested: bool = False
    hang: bool = False
    safe_state: str = ""
    exited_at: float = 0.0
    safe_at: float = 0.0
    ended: asyncio.Event = field(default_factory=asyncio.Event)
    # The start is done with the run (Supervisor.start_run: marked running, logging and tasks
    # started, or given up): its end waits for this, so a loop that ends during its start (a short
    # run on a loaded machine) is ended after it was started, never started after its end.
    settled: asyncio.Event = field(default_factory=asyncio.Event)
    tasks: list[asyncio.Task[Any]] = field(default_factory=list)
    setpoint: dict[str, Any] = field(default_factory=dict)
    # doorbell thread <-> reader task (server/runs/reader.py)
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    wake_pending: bool = False
    thread_stop: threading.Event = field(default_factory=threading.Event)
    # The reader's next wake-up by its own timer (time.monotonic_ns()), 0: on the doorbell; while
    # `reader_timed` the doorbell thread is parked and `idle_wake` unparks it (server/runs/reader.py).
    wake_at_ns: int = 0
    reader_timed: bool = False
    idle_period: float = 0.05  # with nobody taking its streams: the reader's period (s)
    # The console's output poll waits for the reader's first wake-up after output_due
    # (time.monotonic(); 0: none waits), which sets output_poll (server/runs/reader.py, with_reader).
    output_due: float = 0.0
    output_poll: asyncio.Event = field(default_factory=asyncio.Event)
    # The console's output file (pipe_output's descriptor; -1: not open) and how far it has read
    # it: the reader lets the poll go only once the file has grown (reader.output_due).
    output_fd: int = -1
    output_read: int = 0
    idle_wake: threading.Event = field(default_factory=threading.Event)
    thread: threading.Thread | None = None
    last_state_key: tuple[Any, ...] | None = None
    last_status: chmod.Status | None = None
    last_status_at: float = 0.0  # time.monotonic() of last_status (announce.refresh_state)
    last_missed: int = 0
    last_host_lost: int = 0  # the loop's host_lost count the host_lost alarm last told
    telemetry_sent: int = 0
    telemetry_lost: int = 0
    logging: loglive.RunLogging | None = None  # host log writer, live rerun (server/runs/log_writer.py sets it)
    log_timing: bool = False  # the loop logs per-cycle timing (XRF_LOG_TIMING=1)
    guest: GuestReport | None = None  # which protection layers of the run sandbox hold
    watcher: SafetyWatcher | None = None  # the C thread that makes the outputs safe (server/runs/safety.py)
    watch: WatchResult | None = None  # what it did, once it acted
    watch_final: WatchResult | None = None  # its last result, at the end (a hold's drop, time to rest)
    backup: subprocess.Popen | None = None  # xrf-watch: the reaction if the appliance dies (watch.py)
    end_reason: str = ""  # set by whoever ends the run on purpose (runs.END_REASONS)
    limits: RunLimits | None = None  # its cgroup and file system (server/runs/limits.py)
    limit_alarm: str = ""  # the kind of the limit alarm already published ("memory", ...)
    # The loop broke the rules of its segment (server/runs/corrupt.py): what, once it did; and how a
    # reader of the segment says so (from any thread; run_corrupt.watch sets it).
    corrupt: str = ""
    report_corrupt: Callable[[ChannelsCorrupt], None] | None = None

    @property
    def alive(self) -> bool:
        return self.proc.returncode is None


def remove_shm(name: str) -> None:
    """Unlink a run's shared memory and the run's folder of it in /dev/shm (xrflab.guest)."""
    try:
        path = chmod.shm_path(name)
    except ValueError:
        return
    # The run's folder in /dev/shm is the loop's to fill: removed without following a link in it.
    if path.parent != chmod.SHM_DIR:
        with contextlib.suppress(OSError):
            remove_folder(path.parent)
        return
    with contextlib.suppress(FileNotFoundError):
        path.unlink()
    # A name beside the loop's (then unused, or its own /dev/shm) folder, named after it.
    for suffix in (guest.UNCONFINED_SUFFIX, SEGMENT_LINK_SUFFIX):
        if name.endswith(suffix):
            with contextlib.suppress(OSError):
                remove_folder(chmod.SHM_DIR / name.removesuffix(suffix))
