"""A run's live rerun recording: its log records and telemetry while it runs.

The records the host writer hands over (min/max-decimated to ``LIVE_HZ`` points per second per
variable: a display rate; every record stays in the run's log) and the loop's telemetry are
sent, in batches every ``SEND_PERIOD_S``, to the run's recording (``recording_id = run-<id>``) on
the run's own rerun message proxy (``rerun_servers.LiveProxy``, 127.0.0.1 only); browsers read it
through the appliance (server/http/rerun.py). A run's blueprint has one time-series view per
variable group plus encoders, PWM and Xeno2Ros, each view one entity (a series per variable): a
batch is one message per view, whatever the number of variables (rerun's viewer pays per
message). Sending happens on a thread of its own: the writer's thread only queues (and drops,
counted, when the queue is full). See docs/logging/appliance.md.

Nothing is sent while no viewer reads the run's proxy (``LiveProxy.readers``, counted by the
appliance's read route): the proxy keeps only a few seconds for a late viewer anyway (its window,
rerun_servers.LIVE_WINDOW), and the whole run is in its log, so a stream for nobody was work and
memory for nobody (issue 30 item 4: ~16 % of the idle appliance's Python time). The recording
connects at the first viewer; from then on each batch is the last ``SEND_PERIOD_S`` of records and telemetry, so
a viewer that opens gets the live edge within one batch (its first batch too: of the writer's drain that its
arrival woke, only the last ``SEND_PERIOD_S``). "First viewer" counts from when a live
viewer's page is served (``LiveProxy.expect_viewer``): its wasm app starts and connects seconds
later, by when the recording is connected and the proxy holds the live edge (issue 31 bug 6).

The messages are made and sent by ``rerun_sender.LiveSender`` (gRPC-web to the proxy, one POST per
batch), not by the rerun SDK: the appliance imports neither rerun nor pyarrow (issue 30 item 4).
"""

from __future__ import annotations

import contextlib
import inspect
import itertools
import logging
import queue
import threading
import time
import weakref
from collections.abc import Callable
from types import EllipsisType
from typing import TYPE_CHECKING, Any

import numpy as np

from ..channels.errors import ChannelsCorrupt
from . import logformat
from .rerun_sender import APPLICATION_ID, LiveSender, escape_part
from .rerun_servers import LiveProxy

if TYPE_CHECKING:
    from ..channels import Channels, TelemetryReader

# One logger for a run's host logging, whichever module of it speaks (as before the split).
log = logging.getLogger("xrflab.logs.live")

# The live view is for watching, at a display rate: at most LIVE_HZ points per second per logged
# variable, each bucket of 2 * freq / LIVE_HZ cycles sent as its min and max (``decimate_minmax``:
# a one-cycle spike stays visible, every sample's extreme survives). Every record is in the run's
# log, its downloads and its replay (.rrd): the live view says so (frontend/rerun-tab.js). A
# software-rendered browser pays per point drawn (issue 31 bug 6).
LIVE_HZ = 100.0
TELEMETRY_HZ = 50.0  # telemetry samples per second sent to it (the loop publishes at 50 Hz)
# Each time series of the live blueprint shows the last LIVE_SPAN_S of its data (relative to the
# time cursor, which follows the newest data): a frame draws a bounded number of points, however
# long the viewer has watched. The replay of the whole run has no such bound (convert.rrd_blueprint).
LIVE_SPAN_S = 10.0
BACKLOG_S = 5.0  # at most this much of the loop's records waits for the sending thread (then dropped, counted)
# The live recording is sent in batches this far apart. The viewer pays per message and ingests
# for at most 10 ms a frame: at 0.2 s, chromium drawing without a GPU (frames seconds apart) fell
# minutes behind; at 0.5 s (2.5x fewer messages, +0.3 s on average at the wire) a viewer opened
# mid-run reached the live edge in 25 s (bench/appliance/rerun_lag.py, issue 31 bug 6).
SEND_PERIOD_S = 0.5
# With no viewer the sending thread does not look for one on a timer: a viewer's coming wakes it
# (``LiveProxy.on_viewer``: its page served, or the first reader joined; issue 30 item 4).


def decimate_minmax(bucket: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Min/max decimation of `values` (rows x series; float) whose rows are grouped by `bucket`
    (runs of equal ids, e.g. cycle // n). Each run becomes at most two rows: its first and its last
    row (the index of the output rows, returned as row numbers), carrying in each series the run's
    minimum and maximum, in the order they occurred (a spike up then down stays up then down).
    Both extremes of every series in every bucket survive exactly; only their time moves within
    the bucket. NaN is ignored unless a series is NaN throughout a bucket."""
    n = len(values)
    if n == 0:
        return np.zeros(0, dtype=np.intp), values
    starts = np.flatnonzero(np.r_[True, bucket[1:] != bucket[:-1]])
    ends = np.r_[starts[1:], n]
    counts = ends - starts
    lo = np.fmin.reduceat(values, starts, axis=0)
    hi = np.fmax.reduceat(values, starts, axis=0)
    pos = np.arange(n)[:, None]
    at_lo = np.minimum.reduceat(np.where(values == np.repeat(lo, counts, axis=0), pos, n), starts, axis=0)
    at_hi = np.minimum.reduceat(np.where(values == np.repeat(hi, counts, axis=0), pos, n), starts, axis=0)
    lo_first = at_lo <= at_hi
    pairs = np.stack([np.where(lo_first, lo, hi), np.where(lo_first, hi, lo)], axis=1)
    rows = np.stack([starts, ends - 1], axis=1).ravel()
    keep = np.stack([np.ones(len(starts), dtype=bool), counts > 1], axis=1).ravel()  # one row: once
    return rows[keep], pairs.reshape(-1, values.shape[1])[keep]


APP_ID = APPLICATION_ID  # the live recordings' application: the viewer keeps one blueprint per app
TELEMETRY_VIEWS = ["enc", "pwm", "xeno2ros"]  # the live blueprint's views after the variable groups'


class LiveRerun:
    """One run's live recording: log records (decimated) and telemetry, off the writer's thread."""

    def __init__(
        self, proxy: LiveProxy, ch: Channels, run_id: int, wake_writer: Callable[[], None] | None = None
    ) -> None:
        """`wake_writer`: the run's host writer's ``wake`` (its records come every drain period
        otherwise, up to a second, while nobody watches), called when a viewer is coming."""
        self._proxy = proxy
        self._run_id = run_id
        self._ch = ch
        self._freq = max(1, int(ch.info.get("cycle_freq", 1000)))
        self._bucket = max(1, int(round(2 * self._freq / LIVE_HZ)))  # cycles per min/max pair
        # Full-rate records wait here for the sending thread (which decimates them): bounded by
        # records (BACKLOG_S of the loop's), not by batches, since the writer hands over many small ones.
        # (... wakes the sending thread: a viewer is coming, LiveProxy.expect_viewer)
        self._q: queue.Queue[np.ndarray | None | EllipsisType] = queue.Queue()
        self._queued = 0  # records in _q
        self._queued_lock = threading.Lock()  # held for an addition: the writer thread never waits long
        self._max_queued = int(BACKLOG_S * self._freq)
        self.dropped = 0
        self._wall_offset = time.time_ns() - time.monotonic_ns()
        self._names: list[str] | None = None
        self._groups: dict[str, list[str]] = {}  # log entity -> its variables (record fields)
        self._series: dict[str, list[str]] = {}  # entity -> the series names logged for it
        self.rec: LiveSender | None = None  # the run's recording on its proxy, from the first viewer on
        self._telemetry_reader: TelemetryReader | None = None  # while watched: from the newest sample
        self._telemetry_broken = False  # the segment was found corrupt: no more telemetry
        self._texts: queue.SimpleQueue[dict[str, Any]] = queue.SimpleQueue()  # parameter changes
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._main, name=f"xrf-rerun-{run_id}", daemon=True)
        self._thread.start()
        # (only the queue and a weak reference to the writer: the proxy outlives the run, the
        # recording and the writer, which maps the run's shared memory, must not)
        q = self._q
        writer = weakref.WeakMethod(wake_writer) if inspect.ismethod(wake_writer) else None

        def on_viewer() -> None:
            q.put_nowait(...)
            wake = writer() if writer is not None else None
            if wake is not None:
                wake()  # its records now, not at its next drain

        proxy.on_viewer = on_viewer
        # One look now that on_viewer is set: a viewer that joined before (none was called) is
        # seen by it; one that joins later calls on_viewer.
        q.put_nowait(...)

    def watched(self) -> bool:
        return self._proxy.watched()

    def _connect(self) -> None:
        proxy = self._proxy
        self.rec = LiveSender(lambda: proxy.read_url, f"run-{self._run_id}")  # (its port may change: a restart)
        self.rec.connect()
        self._proxy.recording_connected = True  # its window may hold data from now on (LiveProxy.fresh)

    def feed(self, records: np.ndarray) -> None:
        """From the writer thread: queue the records (the writer's own copy); never blocks. The
        sending thread decimates them. Nothing while no viewer reads the stream."""
        if not self.watched() or "cycle" not in (records.dtype.names or ()) or len(records) == 0:
            return
        with self._queued_lock:
            if self._queued + len(records) > self._max_queued:
                self.dropped += len(records)
                return
            self._queued += len(records)
        self._q.put_nowait(records)

    def param_changes(self, changes: list[dict[str, Any]]) -> None:
        """Applied parameter changes (live tuning; rows as in the run's change table), shown as
        text log entries at params/changes, as in the downloaded .rrd. Queued: sent by the
        sending thread with its next batch (the caller is the appliance's event loop)."""
        for c in changes:
            self._texts.put(c)

    def _send_texts(self) -> None:
        from .rrdfile import CHANGES_ENTITY, change_text

        rows = []
        while not self._texts.empty():
            rows.append(self._texts.get_nowait())
        if not rows:
            return
        assert self.rec is not None
        cycle = np.array([int(c["cycle"]) for c in rows], dtype=np.int64)
        t_s = np.array([float(c["t"]) for c in rows], dtype=np.float64)
        self.rec.texts(CHANGES_ENTITY, cycle, t_s, [change_text(c) for c in rows], "INFO")

    def close(self, then: Callable[[], None] | None = None) -> None:
        """Stop feeding; flushing to the proxy happens in the background: a slow viewer can hold
        the proxy's broadcast (rerun blocks its senders then), and a run's end must not wait.
        `then`: called once flushed (logs/live.py: the proxy may stop after it, not before)."""
        self._stop.set()
        try:
            self._q.put_nowait(None)
        except queue.Full:
            pass

        def done() -> None:
            try:
                flush()
            finally:
                if then is not None:
                    then()

        def flush() -> None:
            self._thread.join()
            if self.rec is None:  # never watched: never connected
                return
            # (the thread's last round sent everything: each round ends with its POST)
            with contextlib.suppress(Exception):
                self.rec.close()
            self.rec = None

        threading.Thread(target=done, name="xrf-rerun-close", daemon=True).start()

    def _indexes(self, cycle: np.ndarray, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The cycle and time (wall-clock ns) timelines of these rows."""
        return cycle.astype(np.int64), t_ns.astype(np.int64) + self._wall_offset

    def _name_series(self, entity: str, names: list[str]) -> None:
        """The series' names of a multi-series entity, once per set of names (static)."""
        if self._series.get(entity) != names:
            self._series[entity] = names
            assert self.rec is not None
            self.rec.series_names(entity, names)

    # One message per entity per batch, and rerun's viewer ingests messages for at most 10 ms per
    # frame (re_viewer's receive_messages): a browser drawing a few frames per second (software
    # rendering, a busy laptop) fell behind a stream of one entity per variable and never caught
    # up (issue 19: 5-9 minutes behind). So one entity per view: a variable group's variables
    # are the series of one entity (log/<group>), as encoders and PWM are; telemetry's Xeno2Ros
    # fields are one entity too. Messages per batch = views, whatever the variable count.
    def _send_records(self, rec: np.ndarray) -> None:
        from .convert import _plain, variable_groups

        sender = self.rec
        assert sender is not None
        header = {name for name, _, _ in logformat.RECORD_HEADER}  # seq, cycle, t_ns
        names = [n for n in rec.dtype.names or () if n not in header]
        if names != self._names:
            self._names = names
            self._groups = {}
            for n, g in variable_groups(names).items():
                self._groups.setdefault(f"log/{escape_part(g)}", []).append(n)
            groups = sorted(set(variable_groups(names).values()))
            sender.blueprint(groups, TELEMETRY_VIEWS, LIVE_SPAN_S, self._freq)
        bucket = rec["cycle"] // self._bucket
        for entity, members in self._groups.items():
            # an array variable (or a char string) is a series per element
            cols = [_plain(rec[n]).astype(np.float64).reshape(len(rec), -1) for n in members]
            self._name_series(
                entity,
                [n if c.shape[1] == 1 else f"{n}[{i}]" for n, c in zip(members, cols) for i in range(c.shape[1])],
            )
            rows, values = decimate_minmax(bucket, np.hstack(cols))  # the same rows for every entity
            sender.scalars(entity, *self._indexes(rec["cycle"][rows], rec["t_ns"][rows]), values)

    def _send_telemetry(self) -> None:
        sender = self.rec
        if self._telemetry_reader is None or sender is None:
            return
        try:
            samples = self._telemetry_reader.read()
        except ChannelsCorrupt:
            # The supervisor's own reader sees the same and stops the run (corrupt_channel);
            # this stream just stops reading the segment.
            self._telemetry_reader = None
            self._telemetry_broken = True
            return
        if not samples:
            return
        step = max(1, int(round(len(samples) / max(1.0, TELEMETRY_HZ * SEND_PERIOD_S))))
        samples = samples[::step]
        cycle = np.array([s.cycle for s in samples], dtype=np.int64)
        t_ns = np.array([s.t_ns for s in samples], dtype=np.int64)
        idx = self._indexes(cycle, t_ns)
        for key in ("enc", "pwm"):
            # one entity per group, a series per channel
            values = np.array([getattr(s, key) for s in samples], dtype=np.float64)
            if values.ndim != 2 or values.shape[1] == 0:
                continue
            self._name_series(f"telemetry/{key}", [str(i + 1) for i in range(values.shape[1])])
            sender.scalars(f"telemetry/{key}", *idx, values)
        fields = samples[0].xeno2ros.keys() if isinstance(samples[0].xeno2ros, dict) else []
        plotted, columns = [], []
        for name in fields:
            try:
                columns.append(np.array([float(s.xeno2ros[name]) for s in samples], dtype=np.float64))
            except (TypeError, ValueError):
                continue  # arrays and strings are not plotted
            plotted.append(name)
        if plotted:
            self._name_series("telemetry/xeno2ros", plotted)
            sender.scalars("telemetry/xeno2ros", *idx, np.column_stack(columns))

    def _take(self, item: np.ndarray | None | EllipsisType, pending: list[np.ndarray]) -> bool:
        """One item of the queue: records to `pending`; True for the end (close)."""
        if isinstance(item, np.ndarray):
            with self._queued_lock:
                self._queued -= len(item)
            pending.append(item)
        return item is None

    def _main(self) -> None:
        # Records arrive in small batches (one per writer drain, up to 50 a second); they are
        # sent in one batch per SEND_PERIOD_S: the viewer's cost is per message, and a browser on
        # a student laptop must keep up with the stream (and with the buffer replayed on connect).
        last_telemetry = last_records = 0.0
        pending: list[np.ndarray] = []
        at_edge = True  # the next records sent are a viewer's first: only the live edge of them
        while True:
            item: np.ndarray | None | EllipsisType
            # Unwatched, nothing is queued (feed drops it) and the thread sleeps until something
            # is: a viewer coming (``on_viewer``, its page served or its first reader joined:
            # `...`) or the run's end (close: None). It looked once a second before, for nobody
            # (issue 30 item 4: a tenth of the idle appliance's CPU). A viewer of a loop that
            # logs nothing yet (before RUN) gets its telemetry from that wake-up on.
            wait_s = SEND_PERIOD_S if self.rec is not None and self.watched() else None
            try:
                item = self._q.get(timeout=wait_s)
            except queue.Empty:
                item = ...  # nothing new: still time to send what is pending
            done = self._take(item, pending)
            done = done or (self._stop.is_set() and self._q.empty())
            if not self.watched():
                # Nobody reads: drop what came (records queued before the last viewer left, the
                # parameter changes) and the telemetry reader; a next viewer starts from then.
                pending.clear()
                at_edge = True
                while not self._texts.empty():
                    self._texts.get_nowait()
                self._telemetry_reader = None
                if done:
                    return
                continue
            if self.rec is None:
                try:
                    self._connect()
                except Exception:
                    log.exception("live rerun unavailable")
                    return
            # Everything queued by now goes with this round's batch, not one drain of the writer
            # a round: a round that took long (the recording's connection at the first viewer,
            # rerun's import with it: 1-2 s under load) left the drains of that time queued behind
            # it, and the first batch, sent then, held records that were already 1.4 s old, the
            # newer ones only 0.5 s later (issue 31 bug 6, session 11).
            while True:
                try:
                    more = self._q.get_nowait()
                except queue.Empty:
                    break
                done = self._take(more, pending) or done
            try:
                if self._telemetry_reader is None and not self._telemetry_broken:
                    self._telemetry_reader = self._ch.telemetry_reader()
                now = time.monotonic()
                if pending and at_edge:
                    # A viewer's first records are the writer's drain woken by its arrival: all it
                    # read since its last drain, up to host_writer.MAX_PERIOD_S (4 s) while nobody
                    # watched. Sent whole, the viewer's first frame began seconds before it opened
                    # (CI: 3.1 s); the live edge is the last SEND_PERIOD_S of them, as every later
                    # batch (the rest is in the run's log and its replay).
                    pending[:] = _live_edge(pending, int(SEND_PERIOD_S * self._freq))
                if pending and (done or now - last_records >= SEND_PERIOD_S):
                    last_records = now
                    at_edge = False
                    runs = _same_dtype_runs(pending)
                    pending.clear()
                    if not done:  # the last bucket may not be complete: it waits for the next batch
                        runs[-1], tail = _split_last_bucket(runs[-1], self._bucket)
                        if len(tail):
                            pending.append(tail)
                    for batch in runs:
                        if len(batch):
                            self._send_records(batch)
                            self._proxy.sent()  # the proxy's window ends at the live edge now (LiveProxy.fresh)
                if done or now - last_telemetry >= SEND_PERIOD_S:
                    last_telemetry = now
                    self._send_telemetry()
                    self._send_texts()
                if self.rec is not None:  # the round's batch: one POST (a failed one is dropped: LiveSender)
                    self.rec.flush()
            except Exception:
                pending.clear()
                log.exception("live rerun")
            if done:
                return


def _split_last_bucket(rec: np.ndarray, bucket: int) -> tuple[np.ndarray, np.ndarray]:
    """`rec` without the rows of its last bucket of cycles, and those rows; a bucket whose last
    cycle is there is complete and stays."""
    ids = rec["cycle"] // bucket
    if rec["cycle"][-1] % bucket == bucket - 1:
        return rec, rec[:0]
    earlier = np.flatnonzero(ids != ids[-1])
    cut = int(earlier[-1]) + 1 if len(earlier) else 0
    return rec[:cut], rec[cut:]


def _live_edge(arrays: list[np.ndarray], cycles: int) -> list[np.ndarray]:
    """The rows of `arrays` (in order) within `cycles` cycles of the newest, dropping arrays left empty."""
    newest = max(int(a["cycle"][-1]) for a in arrays)
    kept = [a[a["cycle"].astype(np.int64) > newest - cycles] for a in arrays]
    return [a for a in kept if len(a)]


def _same_dtype_runs(arrays: list[np.ndarray]) -> list[np.ndarray]:
    """Consecutive arrays of one record layout, concatenated (a new log segment may change it)."""
    return [np.concatenate(list(run)) for _, run in itertools.groupby(arrays, key=lambda a: a.dtype)]
