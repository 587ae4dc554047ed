"""A run's live rerun recording: its log records and telemetry while it runs.

The records the host writer hands over (decimated to ``LIVE_HZ``) and the loop's telemetry are
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
memory for nobody (issue 30 item 4: ~16 % of the idle appliance's Python time, and the rerun SDK,
~65 MB RSS, imported at every run's start). The recording connects (and rerun is imported) at the
first viewer; from then on each batch is the last ``SEND_PERIOD_S`` of records and telemetry, so
a viewer that opens gets the live edge within one batch.
"""

from __future__ import annotations

import itertools
import logging
import queue
import threading
import time
from types import EllipsisType
from typing import TYPE_CHECKING, Any

import numpy as np

from ..channels.errors import ChannelsCorrupt
from . import logformat
from .rerun_servers import LiveProxy

if TYPE_CHECKING:
    from ..channels import Channels, TelemetryReader

# One logger for a run's host logging, whichever module of it speaks (as before the split).
log = logging.getLogger("xrflab.logs.live")

LIVE_HZ = 100.0  # log records per second sent to the live rerun recording
TELEMETRY_HZ = 50.0  # telemetry samples per second sent to it
# The live recording is sent in batches this far apart. The viewer pays per message and ingests
# for at most 10 ms a frame: at 0.2 s, chromium drawing without a GPU (frames seconds apart) fell
# minutes behind; at 0.5 s (2.5x fewer messages, +0.3 s on average at the wire) a viewer opened
# mid-run reached the live edge in 25 s (bench/appliance/rerun_lag.py, issue 31 bug 6).
SEND_PERIOD_S = 0.5


def live_blueprint(names: list[str], telemetry: list[str]):
    import rerun as rr
    import rerun.blueprint as rrb

    from .convert import variable_groups

    groups = sorted(set(variable_groups(names).values()))
    views = [rrb.TimeSeriesView(origin=f"/log/{rr.escape_entity_path_part(g)}", name=f"log: {g}") for g in groups]
    views += [rrb.TimeSeriesView(origin=f"/telemetry/{t}", name=t) for t in telemetry]
    return rrb.Blueprint(rrb.Grid(*views), rrb.TimePanel(timeline="cycle"), collapse_panels=True)


class LiveRerun:
    """One run's live recording: log records (decimated) and telemetry, off the writer's thread."""

    def __init__(self, proxy: LiveProxy, ch: Channels, run_id: int) -> None:
        self._rr: Any = None  # the rerun module, imported at the first viewer (_connect)
        self._proxy = proxy
        self._run_id = run_id
        self._ch = ch
        self._freq = max(1, int(ch.info.get("cycle_freq", 1000)))
        self._every = max(1, int(round(self._freq / LIVE_HZ)))
        self._q: queue.Queue[np.ndarray | None] = queue.Queue(maxsize=256)
        self.dropped = 0
        self._wall_offset = time.time_ns() - time.monotonic_ns()
        self._names: list[str] | None = None
        self._groups: dict[str, list[str]] = {}  # log entity -> its variables (record fields)
        self._series: dict[str, list[str]] = {}  # entity -> the series names logged for it
        self.rec: Any = None  # the run's RecordingStream, from the first viewer on
        self._telemetry_reader: TelemetryReader | None = None  # while watched: from the newest sample
        self._telemetry_broken = False  # the segment was found corrupt: no more telemetry
        self._texts: queue.SimpleQueue[dict[str, Any]] = queue.SimpleQueue()  # parameter changes
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._main, name=f"xrf-rerun-{run_id}", daemon=True)
        self._thread.start()

    def watched(self) -> bool:
        return self._proxy.readers > 0

    def _connect(self) -> None:
        import rerun as rr

        self._rr = rr
        self.rec = rr.RecordingStream("xrflab", recording_id=f"run-{self._run_id}")
        self.rec.connect_grpc(self._proxy.local_url)

    def feed(self, records: np.ndarray) -> None:
        """From the writer thread: keep every k-th record (by cycle) and queue it; never blocks.
        Nothing while no viewer reads the stream."""
        if not self.watched() or "cycle" not in (records.dtype.names or ()):
            return
        keep = records[records["cycle"] % self._every == 0]
        if len(keep) == 0:
            return
        try:
            self._q.put_nowait(keep)
        except queue.Full:
            self.dropped += len(keep)

    def param_changes(self, changes: list[dict[str, Any]]) -> None:
        """Applied parameter changes (live tuning; rows as in the run's change table), shown as
        text log entries at params/changes, as in the downloaded .rrd. Queued: sent by the
        sending thread with its next batch (the caller is the appliance's event loop)."""
        for c in changes:
            self._texts.put(c)

    def _send_texts(self) -> None:
        from .convert import CHANGES_ENTITY, change_text

        rows = []
        while not self._texts.empty():
            rows.append(self._texts.get_nowait())
        if not rows:
            return
        rr = self._rr
        idx = [
            rr.TimeColumn("cycle", sequence=np.array([int(c["cycle"]) for c in rows], dtype=np.int64)),
            rr.TimeColumn("time", timestamp=np.array([float(c["t"]) for c in rows], dtype=np.float64)),
        ]
        cols = rr.TextLog.columns(text=[change_text(c) for c in rows], level=["INFO"] * len(rows))
        self.rec.send_columns(CHANGES_ENTITY, indexes=idx, columns=cols)

    def close(self) -> None:
        """Stop feeding; flushing to the proxy happens in the background: a slow viewer can hold
        the proxy's broadcast (rerun blocks its senders then), and a run's end must not wait."""
        self._stop.set()
        try:
            self._q.put_nowait(None)
        except queue.Full:
            pass

        def done() -> None:
            self._thread.join()
            if self.rec is None:  # never watched: never connected
                return
            try:
                self.rec.flush()
                self.rec.disconnect()
            except Exception:
                pass

        threading.Thread(target=done, name="xrf-rerun-close", daemon=True).start()

    def _indexes(self, cycle: np.ndarray, t_ns: np.ndarray) -> list[Any]:
        rr = self._rr
        return [
            rr.TimeColumn("cycle", sequence=cycle.astype(np.int64)),
            rr.TimeColumn("time", timestamp=(t_ns.astype(np.int64) + self._wall_offset).view("datetime64[ns]")),
        ]

    def _name_series(self, entity: str, names: list[str]) -> None:
        """The series' names of a multi-series entity, once per set of names (static)."""
        if self._series.get(entity) != names:
            self._series[entity] = names
            self.rec.log(entity, self._rr.SeriesLines(names=names), static=True)

    # One message per entity per batch, and rerun's viewer ingests messages for at most 10 ms per
    # frame (re_viewer's receive_messages): a browser drawing a few frames per second (software
    # rendering, a busy laptop) fell behind a stream of one entity per variable and never caught
    # up (issue 19: 5-9 minutes behind). So one entity per view: a variable group's variables
    # are the series of one entity (log/<group>), as encoders and PWM are; telemetry's Xeno2Ros
    # fields are one entity too. Messages per batch = views, whatever the variable count.
    def _send_records(self, rec: np.ndarray) -> None:
        from .convert import _plain, variable_groups

        rr = self._rr
        header = {name for name, _, _ in logformat.RECORD_HEADER}  # seq, cycle, t_ns
        names = [n for n in rec.dtype.names or () if n not in header]
        if names != self._names:
            self._names = names
            self._groups = {}
            for n, g in variable_groups(names).items():
                self._groups.setdefault(f"log/{rr.escape_entity_path_part(g)}", []).append(n)
            self.rec.send_blueprint(live_blueprint(names, ["enc", "pwm", "xeno2ros"]))
        idx = self._indexes(rec["cycle"], rec["t_ns"])
        for entity, members in self._groups.items():
            # an array variable (or a char string) is a series per element
            cols = [_plain(rec[n]).astype(np.float64).reshape(len(rec), -1) for n in members]
            self._name_series(
                entity,
                [n if c.shape[1] == 1 else f"{n}[{i}]" for n, c in zip(members, cols) for i in range(c.shape[1])],
            )
            self.rec.send_columns(entity, indexes=idx, columns=rr.Scalars.columns(scalars=np.hstack(cols)))

    def _send_telemetry(self) -> None:
        rr = self._rr
        if self._telemetry_reader is None:
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
            self.rec.send_columns(f"telemetry/{key}", indexes=idx, columns=rr.Scalars.columns(scalars=values))
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
            self.rec.send_columns(
                "telemetry/xeno2ros", indexes=idx, columns=rr.Scalars.columns(scalars=np.column_stack(columns))
            )

    def _main(self) -> None:
        # Records arrive in small batches (one per writer drain, up to 50 a second); they are
        # sent in one batch per SEND_PERIOD_S: the viewer's cost is per message, and a browser on
        # a student laptop must keep up with the stream (and with the buffer replayed on connect).
        last_telemetry = last_records = 0.0
        pending: list[np.ndarray] = []
        while True:
            item: np.ndarray | None | EllipsisType
            try:
                item = self._q.get(timeout=SEND_PERIOD_S)
            except queue.Empty:
                item = ...  # nothing new: still time to send what is pending
            if isinstance(item, np.ndarray):
                pending.append(item)
            done = item is None or (self._stop.is_set() and self._q.empty())
            if not self.watched():
                # Nobody reads: drop what came (records queued before the last viewer left, the
                # parameter changes) and the telemetry reader; a next viewer starts from then.
                pending.clear()
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
            try:
                if self._telemetry_reader is None and not self._telemetry_broken:
                    self._telemetry_reader = self._ch.telemetry_reader()
                now = time.monotonic()
                if pending and (done or now - last_records >= SEND_PERIOD_S):
                    last_records = now
                    for batch in _same_dtype_runs(pending):
                        self._send_records(batch)
                    pending.clear()
                if done or now - last_telemetry >= SEND_PERIOD_S:
                    last_telemetry = now
                    self._send_telemetry()
                    self._send_texts()
            except Exception:
                pending.clear()
                log.exception("live rerun")
            if done:
                return


def _same_dtype_runs(arrays: list[np.ndarray]) -> list[np.ndarray]:
    """Consecutive arrays of one record layout, concatenated (a new log segment may change it)."""
    return [np.concatenate(list(run)) for _, run in itertools.groupby(arrays, key=lambda a: a.dtype)]
