"""Runs a dead appliance left behind (it was killed with kill -9, or crashed, mid-run).

The loop does not die with the appliance: it notices the host heartbeat stop and does what
``host_timeout_action`` says (pause or stop; its outputs stay safe), and its run record still
says it is live. The restarted appliance closes each such run before it takes a new one (the
supervisor holds the bench lock meanwhile): it maps the run's shared memory if it is still
there, picks up the loop's log ring where the dead appliance left it (the read position lives in
the shared memory, so a new host writer appends a segment to the same file, skipping what was
already written), stops the loop through its launcher, and records the run's real counts and
what happened, with ``end_reason`` ``appliance_restart``. A `hold` run's xrf-watch outlived the
dead appliance and already killed the loop and put the arm down: its record in the run folder
(server/runs/watch_record.py, waited for while the arm is still being lowered) says what it did,
kept with the run (``safe_outcome``), and the run ends ``appliance_gone``.

The launcher is found from the controller's pid (``row.pid``) and only trusted if its
environment names this run's folder: a pid may have been reused by anything since.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import time
from pathlib import Path
from typing import Any

from ... import channels as chmod
from ...channels import Channels, ChannelsError, segment
from ...logs import live as loglive
from ..settings import Settings
from ..ws.hub import Hub
from ..ws.messages import AlarmMessage, RunMessage
from . import watch_record
from .run import remove_shm
from .store import RunRow, RunStore
from .watch import run_safe_reaction

log = logging.getLogger("xrflab.supervisor")


def parent_of(pid: int) -> int:
    """The parent pid from /proc/<pid>/stat (world-readable, whoever owns the process); 0 if gone."""
    try:
        return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return 0


def alive(pid: int) -> bool:
    """The process exists and is not a zombie."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def last_logged_seq(ch: Channels, run_dir: Path) -> int | None:
    """The `seq` of the last record in the run's log file (the one the loop's log_meta names),
    None if there is none yet."""
    from ...logs.log_channel import LogChannel
    from ...logs.reader import open_log
    from ...runfolder import RunFolder, RunPathError, confine

    try:  # the layout as every reader takes it: copied and checked (log_channel.py)
        layout = LogChannel(ch, "log").take_layout()
    except ChannelsError:
        return None
    if layout is None:
        return None
    try:
        rel = confine(run_dir, layout.path)
        with RunFolder(run_dir) as rf:  # the loop named it: through the run folder's helper
            fd = rf.open_mappable(rel)
        try:
            records = open_log(run_dir / rel, fd=fd).records
        finally:
            os.close(fd)
    except (RunPathError, OSError, ValueError, KeyError):  # no file yet, or nothing readable in it
        return None
    return int(records["seq"][-1]) if len(records) else None


def launcher_of(row: RunRow) -> int:
    """The launcher of an orphaned run's loop, only if it really is this run's launcher (its
    XRF_RUN_DIR names the run folder); 0 if there is none. ``row.pid`` is the controller; its
    parent is the sandbox's init (guest._init) or, without a PID namespace, the launcher
    itself, which runs as our own uid in every sandbox mode (so its environ is ours to read)."""
    want = f"XRF_RUN_DIR={row.run_dir}".encode()
    found, pid = 0, row.pid or 0
    for _ in range(2):  # the init, then the launcher above it: the topmost that matches
        pid = parent_of(pid) if pid else 0
        if pid <= 1 or not row.run_dir:
            break
        try:
            environ = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
        except OSError:
            continue  # the init, as the loop's user, may not be ours to read; its parent is
        if want in environ:
            found = pid
    return found


def abandon(row: RunRow) -> None:
    """Recovering the run failed: whatever failed, the loop does not run on unsupervised."""
    launcher = launcher_of(row)
    if launcher:
        with contextlib.suppress(ProcessLookupError):
            os.kill(launcher, signal.SIGKILL)
    if row.shm:
        remove_shm(row.shm)


def open_segment(row: RunRow) -> Channels:
    """The orphaned run's segment. A run of this appliance's has a sealed memfd, which its
    launcher keeps open as XRF_SHM_FD (server/runs/guest_spawn.py): reopened through /proc/<launcher>/fd,
    only when the launcher is this run's (launcher_of). The name's link pointed at the dead
    appliance's descriptor and is not followed (its pid may be anyone's now). A segment of an
    older appliance's run is a file of that name."""
    launcher = launcher_of(row)
    if launcher:
        environ = Path(f"/proc/{launcher}/environ").read_bytes().split(b"\0")
        number = next((v.split(b"=", 1)[1] for v in environ if v.startswith(b"XRF_SHM_FD=")), b"")
        if number.isdigit():
            fd = os.open(f"/proc/{launcher}/fd/{int(number)}", os.O_RDWR | os.O_CLOEXEC)
            try:
                if not segment.is_sealed(fd):
                    raise ChannelsError(f"{row.shm}: the launcher's XRF_SHM_FD is not a sealed segment")
                return Channels.open_fd(fd, row.shm, 0.2)
            finally:
                os.close(fd)
    path = chmod.shm_path(row.shm)
    if path.is_symlink():
        raise ChannelsError(f"{row.shm}: the segment went with its launcher")
    return Channels.open(row.shm, 0.2)


async def recover(row: RunRow, settings: Settings, store: RunStore) -> RunRow:
    """Close one orphaned run: its final record (the run observers and the browsers are told by
    the supervisor, `announce`); its shared memory is unlinked when this returns."""
    ch: Channels | None = None
    if row.shm:
        with contextlib.suppress(Exception):
            ch = await asyncio.to_thread(open_segment, row)
    writer = None
    if ch is not None and row.run_dir and Path(row.run_dir).is_dir():
        # The ring's read position lives in the shared memory: a new writer goes on where the
        # dead appliance stopped, appending a segment to the same file.
        identity = {"project": row.build, "build": row.build, "run": str(row.id)}
        writer = loglive.HostLogWriter(ch, identity, Path(row.run_dir))
        last_seq = await asyncio.to_thread(last_logged_seq, ch, Path(row.run_dir))
        if last_seq is not None:
            writer.skip_through(last_seq)  # written by the dead appliance, not yet released
        writer.start()
    before = None
    if ch is not None:
        with contextlib.suppress(ChannelsError):  # locked by a loop stopped mid-write: none
            before = ch.status()
    launcher = launcher_of(row)
    stopped_at = 0.0
    if launcher:
        log.warning("run %s: stopping loop pid %s left by a previous appliance", row.id, row.pid)
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            with contextlib.suppress(ProcessLookupError):
                os.kill(launcher, sig)
            deadline = time.monotonic() + settings.signal_timeout_s
            while alive(launcher) and time.monotonic() < deadline:
                await asyncio.sleep(0.02)
            if not alive(launcher):
                break
        stopped_at = time.time()
    stats = await asyncio.to_thread(writer.finish) if writer is not None else None
    watched = await watcher_outcome(row, settings)
    last = before
    if ch is not None:
        with contextlib.suppress(ChannelsError):
            last = ch.status()
    records = 0
    if stats is not None:
        from ...logs.reader import open_log

        for path in dict.fromkeys(stats.files):  # the old appliance's segments and ours
            with contextlib.suppress(Exception):
                records += len(open_log(path))
    parts = ["the appliance stopped while this run was live"]
    gone = watched.outcome is not None and watched.outcome["reason"] == "host_gone"
    if watched.outcome is not None and gone:
        parts.append(watch_record.describe(watched.outcome))
    elif watched.problem:
        parts.append(watched.problem)
    if ch is not None and last is not None:
        lost_at = ch.shm.host_heartbeat_ns
        if lost_at:
            ago = (time.monotonic_ns() - int(lost_at)) / 1e9
            parts.append(f"its last heartbeat was at {time.strftime('%H:%M:%S', time.localtime(time.time() - ago))}")
        if last.host_lost:
            parts.append(
                f"the loop then did what host_timeout_action says "
                f"({settings.host_timeout_action} after {settings.host_timeout_ms} ms)"
            )
    if stopped_at and not gone:
        parts.append(f"the restarted appliance stopped it at {time.strftime('%H:%M:%S', time.localtime(stopped_at))}")
    elif row.pid and not alive(row.pid) and not gone:
        parts.append("the loop had already ended")
    values: dict[str, Any] = {
        "status": "crashed",
        "crashed": 1,
        "crash_reason": "appliance",
        "end_reason": "appliance_gone" if gone else "appliance_restart",
        "message": "; ".join(parts),
        "ended": stopped_at or row.ended or time.time(),
        "safe_outcome": watched.outcome if gone else None,
    }
    if last is not None:
        values.update(state=last.state_name, cycles=last.cycles, misses=last.missed)
    if stats is not None:
        values.update(log_records=records, log_lost=stats.lost + stats.unwritten, log_note=stats.failed)
    final = store.update(row.id, **values)
    if row.shm:
        remove_shm(row.shm)
    return final


# How long a restart waits for a run's xrf-watch still lowering the arm: the law's own bound
# (xrf_hold_arm.max_s, 20 s for the youBot) and some room; then the record is taken as it is.
WATCHER_WAIT_S = 25.0


def is_watcher(pid: int) -> bool:
    """`pid` is alive and an xrf-watch (the pid came from a file the guest could write)."""
    try:
        return alive(pid) and Path(f"/proc/{pid}/comm").read_text().strip() == "xrf-watch"
    except OSError:
        return False


async def watcher_outcome(row: RunRow, settings: Settings) -> watch_record.Read:
    """The run's xrf-watch record (server/runs/watch_record.py), once it is done: while it says
    the arm is still being lowered and its xrf-watch is still there, wait (bounded), so the run
    is recorded with the arm at rest. Only a `hold` run has an xrf-watch (watch.start_backup): in
    any other run's folder a file of that name is the guest's, never read."""
    if not row.run_dir or run_safe_reaction(row.sim, settings.bench_is_real(), settings).name != "hold":
        return watch_record.Read(None, "")
    deadline = time.monotonic() + WATCHER_WAIT_S
    while True:
        got = await asyncio.to_thread(watch_record.read, row.run_dir)
        if not got.pid or time.monotonic() > deadline:  # no pid: done (or no record)
            return got
        if not is_watcher(got.pid):
            # Gone since the read above: its last record (written before it ended) may be the
            # "done" one this read just missed (CI: a restart recorded done: False with the arm at
            # rest). Read once more, after its end.
            return await asyncio.to_thread(watch_record.read, row.run_dir)
        await asyncio.sleep(0.1)  # polling: xrf-watch is another session's process, no descriptor of ours


def announce(row: RunRow, hub: Hub) -> None:
    """Tell the browsers a recovered run ended (after the run observers heard it)."""
    hub.publish(AlarmMessage(kind="crash", end_reason=row.end_reason, run_id=row.id, message=row.message))
    hub.publish(RunMessage(event="ended", run=row.as_dict(), active=False))
