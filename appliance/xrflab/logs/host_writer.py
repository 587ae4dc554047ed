"""The host log writer: a thread of the appliance that writes a run's log files.

When the loop runs with ``XRF_LOG_WRITER=host``, a thread of the appliance drains the loop's
lossless log ring (``log_channel.py``: the longest run of ready slots that is contiguous, one
``write()`` each) into the file named in ``log_meta.path``, in the format of
docs/logging/file-format.md; each segment header comes from rt_core's ``xrf_logfile_header``
(logformat.h, through cffi: the function the loop's own writer calls, so the bytes are the same
whichever side writes). A new layout (the channel's generation) starts a new segment, appended
to the file the loop names then. It drains in batches, a period apart (``drain_period``): the
ring holds ``slots`` records and the loop adds at most one a cycle, so a drain every
``slots / cycle_freq / RING_MARGIN`` seconds (at most ``MAX_PERIOD_S``) finds the ring at most a
quarter full and nothing is lost to waiting; a drain that finds it fuller than that halves the
period from then on. Each contiguous run of records is one ``write()`` of the ring's bytes, with no
per-record Python work. While a live rerun viewer reads the run (``fast()``), it drains every
``WAIT_MS`` instead so the viewer stays near the live edge. (It used to wake on every doorbell,
~50-80 times a second for a RELbot, to write ~20 records each time: issue 30 item 4.) Because the appliance keeps the run's shared memory mapped after the
loop process is gone, a crashed or killed loop loses nothing that reached the ring: ``finish()``
drains the rest.

A loop that breaks the rules of its log channel (a layout the logger never publishes, a ring
head beyond what the ring holds: log_channel.py checks both) stops this writer: the file keeps
its complete records up to there, nothing of the segment is read again, and ``on_corrupt``
tells the supervisor, which stops the run (``corrupt_channel``).

Faults: the loop never waits on us: if we stall, the ring fills and the loop counts
``log_lost`` (sequence numbers make the gap visible). A write that fails (disk full, I/O error,
file too large) stops logging for the run, cuts the file back to its last complete record
(``record_file.py``: what was written stays decodable) and raises an alarm once; records drained
after that are counted as ``unwritten`` so the run record still adds up: ``seq`` of the last
record + 1 = records in the file + lost + unwritten.

The same thread writes the run's timing series (``timing_series.py``: sampled once a second by
the caller, the appliance's timing task, with ``timing_in_thread`` False; else by this thread)
and, while someone takes
them live (``fast()``: a live rerun viewer is open), hands each drained batch of records to
``on_records`` (the live rerun stream, ``rerun_live.py``); with nobody there no copy is made.
"""

from __future__ import annotations

import logging
import os
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..channels.errors import ChannelsCorrupt
from ..runfolder import RunPathError, confine
from .log_channel import LogChannel, SegmentLayout
from .record_file import PartialWrite, RecordFile
from .timing_series import TimingSeries

if TYPE_CHECKING:
    from ..channels import Channels
    from ..channels.binding import CData

# One logger for a run's host logging, whichever module of it speaks (as before the split).
log = logging.getLogger("xrflab.logs.live")

WAIT_MS = 20  # between two drains while someone watches the records live (fast())
# Between two drains otherwise: how stale the file on disk may be while the run goes on (its end
# drains the rest: finish(); a live rerun viewer gets WAIT_MS). 4 s of a RELbot's records is a
# sixteenth of its ring (65 536 slots); it was 1 s (issue 30 item 4: the thread still wakes once a
# second for the timing series' line, the drain's Python and write now every fourth time).
MAX_PERIOD_S = 4.0
RING_MARGIN = 4  # a drain is due when the ring could be a quarter full at one record a cycle


def drain_period(slots: int, cycle_freq: int) -> float:
    """Seconds between two drains of a ring of `slots` records filled at most once a cycle at
    `cycle_freq` Hz: a quarter of the time the ring takes to fill, at most MAX_PERIOD_S, at least
    WAIT_MS (a tiny ring at a high rate is drained as often as before)."""
    if slots <= 0 or cycle_freq <= 0:
        return WAIT_MS / 1000
    return min(MAX_PERIOD_S, max(WAIT_MS / 1000, slots / cycle_freq / RING_MARGIN))


@dataclass
class WriterStats:
    files: list[str] = field(default_factory=list)  # paths written, in order
    records: int = 0  # records in the files
    unwritten: int = 0  # drained after a write failure, so not in any file
    bytes: int = 0
    failed: str = ""  # why logging stopped ("" = it did not)
    lost: int = 0  # the loop's ring drops (status.log_lost), filled in by finish()


class HostLogWriter:
    """Drains one log channel of a run (`source`: the logger's ring, or the per-cycle timing
    records) into its file; a thread of the appliance."""

    def __init__(
        self,
        ch: Channels,
        identity: dict[str, str],
        run_dir: Path,
        on_alarm: Callable[[str], None] | None = None,
        on_records: Callable[[np.ndarray], None] | None = None,
        timing: bool = True,
        source: str = "log",
        on_note: Callable[[str], None] | None = None,
        on_corrupt: Callable[[ChannelsCorrupt], None] | None = None,
        fast: Callable[[], bool] | None = None,
        timing_in_thread: bool = True,
    ) -> None:
        """`fast()`: someone takes the records live (on_records): drain every WAIT_MS then.
        `timing_in_thread` False: the timing series' samples are taken by the caller, once a
        second (`take_timing`: the appliance's timing task, which wakes then anyway), and this
        thread writes their lines at its drains, so it does not wake once a second for them."""
        self._timing_in_thread = timing_in_thread
        self._ch = ch
        self._fast = fast
        self._chan = LogChannel(ch, source)
        self._source = source
        self._identity = identity
        self._run_dir = run_dir
        self._on_alarm = on_alarm
        self._on_note = on_note
        self._on_records = on_records
        self._on_corrupt = on_corrupt
        self.corrupt = ""  # what the loop broke, once it did: nothing is read from then on
        self._timing = TimingSeries(ch, run_dir) if timing else None
        self.stats = WriterStats()
        self._file: RecordFile | None = None
        self._generation = 0
        self._stride = 0
        self._dtype: np.dtype | None = None
        self._stop = threading.Event()
        self._woken = threading.Event()  # drain now, not at the period's end (wake)
        self._lock = threading.Lock()  # one drain at a time (thread vs finish())
        self._halved = 0  # times a drain found the ring fuller than planned (the period halves)
        self.drains = 0  # drains that took records (tests, the footprint benchmark)
        self.wakeups = 0  # turns of the thread's loop (tests: how often it wakes)
        self._thread: threading.Thread | None = None

    # -- life cycle -------------------------------------------------------------------------

    def start(self) -> None:
        self._thread = threading.Thread(target=self._main, name=f"xrf-{self._source}-writer", daemon=True)
        self._thread.start()

    def finish(self) -> WriterStats:
        """Stop the thread and drain what is left (the loop may be dead: the mapping is ours)."""
        self._stop.set()
        self._woken.set()
        if self._thread is not None:
            self._thread.join(5.0)
        self.drain(final=True)
        with self._lock:
            if self._file is not None:
                self._file.close(sync=True)
                self._file = None
        if self._source != "log":
            self.stats.lost = self._chan.dropped()
            return self.stats
        try:
            status = self._ch.status()
            self.stats.lost = int(status.log_lost)
            if self._chan.taken and not self._chan.host_writes():
                self.stats.records = int(status.log_written)  # XRF_LOG_WRITER=process wrote them
        except Exception:  # status locked by a loop that died mid-write: the ring knows too
            self.stats.lost = self._chan.dropped()
        self._sample_timing(force=True)
        if self._timing is not None:
            self._timing.close()
        return self.stats

    def _main(self) -> None:
        next_drain = 0.0  # time.monotonic() of the next drain
        while not self._stop.is_set():
            self.wakeups += 1
            try:
                now = time.monotonic()
                if now >= next_drain:
                    taken = self.drain()
                    if taken > self._chan.slots() // RING_MARGIN > 0:
                        self._halved += 1  # the loop logs faster than once a cycle: drain more often
                    next_drain = now + self.period()
                    if self._timing is not None and not self._timing_in_thread:
                        self._timing.write_pending()  # the samples take_timing took meanwhile
                if self._timing_in_thread:
                    self._sample_timing()
            except Exception:  # never let a bug end logging silently
                log.exception("log writer")
                time.sleep(0.1)
            # A timed sleep, not the doorbell: the loop rings it for its telemetry (50 Hz and
            # more), far more often than a ring of seconds of records needs draining. Until the
            # next drain or the timing series' next line (once a second), whichever is first.
            wait = max(0.0, next_drain - time.monotonic())
            if self._timing is not None and self._timing_in_thread:
                wait = min(wait, self._timing.due_in())
            if self._woken.wait(wait):
                next_drain = 0.0  # wake(): drain now
            self._woken.clear()

    def take_timing(self, copy: CData | None = None) -> None:
        """A sample of the timing series now, if one is due (`timing_in_thread` False: called
        once a second by the appliance's timing task, with its status copy); its line is written
        at the next drain."""
        if self._timing is not None:
            self._timing.take(copy=copy)

    def flush_timing(self) -> None:
        """The lines of the samples taken so far written now (a reader of timing.jsonl of the
        running run: it is written at the drains, every few seconds, otherwise)."""
        if self._timing is not None:
            self._timing.write_pending()

    def wake(self) -> None:
        """Drain now rather than at the end of the period: a live viewer is coming (``fast()`` has
        just turned true; the live stream's ``LiveRerun`` calls it). Without it, the records it
        waits for came with the next periodic drain, up to ``MAX_PERIOD_S`` later (issue 31 bug 6,
        session 11: a viewer's first data, and the read route's wait for the recording to resume)."""
        self._woken.set()

    def period(self) -> float:
        """Seconds until the next drain (see the module's docstring)."""
        if self._fast is not None and self._fast():
            return WAIT_MS / 1000
        p = drain_period(self._chan.slots(), int(self._ch.info.get("cycle_freq", 0) or 0))
        return max(WAIT_MS / 1000, p / (2 ** min(self._halved, 16)))

    def skip_through(self, last_seq: int) -> int:
        """Release the ring's records numbered <= `last_seq` without writing them: a dead
        appliance wrote them to the file but was killed before it released them (the read
        position lives in shared memory). Call before start(). Returns how many were skipped."""
        with self._lock:
            try:
                return self._skip_through(last_seq)
            except ChannelsCorrupt as exc:
                self._corrupted(exc)
                return 0

    def _skip_through(self, last_seq: int) -> int:
        if not self._chan.taken:
            layout = self._chan.take_layout() if self._chan.ready() else None
            if layout is None:
                return 0
            # The segment is opened as the dead appliance's was: the same generation, appended.
            self._open_segment(layout)
        stride = self._chan.slot_size()
        skipped = 0
        while skipped < 2 * self._chan.slots():  # bounded as a drain is
            run = self._chan.peek_run()
            if run is None:
                return skipped
            buf, n = run
            k = 0
            while k < n and struct.unpack_from("<Q", buf, k * stride)[0] <= last_seq:  # seq: the header's first word
                k += 1
            if k:
                self._chan.release(k)
                skipped += k
            if k < n:
                return skipped
        return skipped

    def set_on_records(self, fn: Callable[[np.ndarray], None] | None, fast: Callable[[], bool] | None = None) -> None:
        with self._lock:
            self._on_records = fn
            self._fast = fast

    # -- draining ----------------------------------------------------------------------------

    def drain(self, final: bool = False) -> int:
        """Write every ready record; returns how many were taken from the ring."""
        with self._lock:
            if self.corrupt:
                return 0
            try:
                return self._drain()
            except ChannelsCorrupt as exc:
                self._corrupted(exc)
                return 0

    def _corrupted(self, exc: ChannelsCorrupt) -> None:
        """The loop broke its log channel: stop here (the file ends at its last whole record)
        and tell the supervisor, once."""
        if self.corrupt:
            return
        self.corrupt = str(exc)
        log.error("%s", exc)
        if self._file is not None:
            self._file.close()
            self._file = None
        if self._on_corrupt is not None:
            self._on_corrupt(exc)

    def _drain(self) -> int:
        if not self._chan.ready():
            return 0
        if self._chan.generation() != self._generation:
            layout = self._chan.take_layout()
            if layout is None:
                return 0  # being published: the next drain takes it
            self._open_segment(layout)
        if not self._chan.host_writes():
            return 0
        taken = 0
        # At most two rings' worth a drain: a loop that moves its head as fast as we release
        # cannot keep this thread (and finish(), waiting for the lock) here.
        budget = 2 * self._chan.slots()
        # The records go to on_records (the live rerun stream) only while someone takes them live
        # (fast(): a viewer is open); with nobody there the stream drops them anyway, and the copy
        # of every drained record with its array was work for nobody (issue 30 item 4).
        live = self._on_records is not None and self._dtype is not None and (self._fast is None or self._fast())
        while taken < budget:
            run = self._chan.peek_run()
            if run is None:
                break
            buf, n = run
            if live and self._on_records is not None:
                # A copy: the slots are reused as soon as they are released.
                self._on_records(np.frombuffer(bytes(buf), dtype=self._dtype))
            self._write(buf, n)
            self._chan.release(n)
            taken += n
        if taken:
            self.drains += 1
        return taken

    def _open_segment(self, layout: SegmentLayout) -> None:
        """A new segment of the file for a layout just taken (LogChannel.take_layout)."""
        self._generation = self._chan.taken_generation
        self._stride = layout.stride
        self._dtype = layout.dtype
        if self._file is not None:
            self._file.close()
            self._file = None
        if self.stats.failed or not self._chan.host_writes():
            return  # logging stopped, or the loop's own writer writes this layout
        published = layout.path
        # The loop names the file and is not trusted: the name is confined to the run folder
        # and opened without following symlinks (runfolder.py), whatever the loop published.
        try:
            rel = confine(self._run_dir, published)
        except RunPathError as exc:
            self._fail(f"{exc}: refused, not logged", published)
            return
        path = str(self._run_dir / rel)
        try:
            self._file = RecordFile.open(self._run_dir, rel, layout.file_mode, layout.stride)
            self._file.write_all(self.segment_header())
        except OSError as exc:
            self._fail(f"cannot write the log file {rel} of the run: {exc.strerror or exc}", path)
            return
        self.stats.files.append(path)
        if self._on_note is not None:
            # Where the file went, in the console: an XRF2 name like /home/x/logs/log is not
            # where the student will find it (the runtime says so too, at set-up).
            outside = os.path.isabs(published) and not published.startswith(str(self._run_dir) + "/")
            shown = published if outside else rel
            self._on_note(f"log {shown} -> {self._run_dir.parent.name}/{self._run_dir.name}/{rel}")

    def segment_header(self, start_unix_ns: int | None = None, start_mono_ns: int | None = None) -> bytes:
        """The header of a segment of the channel's current layout, starting now (or at the given
        clocks), with the run's identity (LogChannel.segment_header)."""
        return self._chan.segment_header(self._identity, start_unix_ns, start_mono_ns)

    def _write(self, buf: memoryview, n: int) -> None:
        if self._file is None:
            self.stats.unwritten += n
            return
        try:
            self._file.append(buf, n)
        except PartialWrite as cut:
            # Whole records only: the file ends at its last complete record.
            self.stats.records += cut.done
            self.stats.bytes += cut.done * self._stride
            self.stats.unwritten += n - cut.done
            self._fail(
                f"writing the log file failed ({cut.error.strerror or cut.error}) after "
                f"{self.stats.records} records; logging stopped, the run goes on",
                self.stats.files[-1] if self.stats.files else "",
            )
            return
        self.stats.records += n
        self.stats.bytes += n * self._stride

    def _fail(self, message: str, path: str) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None
        if not self.stats.failed:
            self.stats.failed = message
            log.error("%s", message)
            if self._on_alarm is not None:
                self._on_alarm(message)

    def _sample_timing(self, force: bool = False) -> None:
        if self._timing is not None:
            self._timing.sample(force)
