"""The appliance side of a run's logging: the host log writer, the per-second timing series and
the live rerun stream.

**Host log writer** (the loop runs with ``XRF_LOG_WRITER=host``): a thread of the appliance
drains the loop's lossless log ring (``xrf_spsc_peek_run``: the longest run of ready slots that
is contiguous, one ``write()`` each) into the file named in ``log_meta.path``, in the format of
docs/logging/file-format.md; each segment header comes from rt_core's ``xrf_logfile_header``
(logformat.h, through cffi: the function the loop's own writer calls, so the bytes are the same
whichever side writes). It wakes on the loop's doorbell (futex, no polling; at most ``WAIT_MS``
between drains). Because the appliance keeps the run's shared memory mapped after the loop
process is gone, a crashed or killed loop loses nothing that reached the ring: ``finish()``
drains the rest.

Faults: the loop never waits on us: if we stall, the ring fills and the loop counts
``log_lost`` (sequence numbers make the gap visible). A write that fails (disk full, I/O error,
file too large) stops logging for the run, cuts the file back to its last complete record (what
was written stays decodable) and raises an alarm once; records drained after that are counted
as ``unwritten`` so the run record still adds up: ``seq`` of the last record + 1 = records in the
file + lost + unwritten.

**Timing** (issue 4 item 2, without an rt_core change): once per second the framework's stage
histograms are sampled into ``timing.jsonl`` in the run folder: per stage the interval's count,
mean, and the cumulative p50/p99/max, wake-up jitter included.

**Live rerun**: the records the writer hands over (decimated to ``LIVE_HZ``) and the loop's
telemetry are sent, in batches every ``SEND_PERIOD_S``, to the run's recording
(``recording_id = run-<id>``) on the run's own rerun message proxy (``LiveProxy``, 127.0.0.1
only); browsers read it through the appliance (server/routes_rerun.py). A run's blueprint has one
time-series view per variable group plus encoders, PWM and Xeno2Ros, each view one entity (a series
per variable): a batch is one message per view, whatever the number of variables (rerun's viewer
pays per message). See docs/logging/appliance.md.
"""

from __future__ import annotations

import atexit
import contextlib
import itertools
import json
import logging
import os
import queue
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import EllipsisType
from typing import Any

import numpy as np

from . import logformat
from .runfolder import RunPathError, confine, open_in

log = logging.getLogger("xrflab.logs.live")

WAIT_MS = 20  # longest time between two drains when no doorbell rings
LIVE_HZ = 100.0  # log records per second sent to the live rerun recording
TELEMETRY_HZ = 50.0  # telemetry samples per second sent to it
SEND_PERIOD_S = 0.2  # the live recording is sent in batches this far apart
RERUN_NICE = 10  # rerun's child processes run below the appliance
TIMING_PERIOD_S = 1.0


@dataclass
class WriterStats:
    files: list[str] = field(default_factory=list)  # paths written, in order
    records: int = 0  # records in the files
    unwritten: int = 0  # drained after a write failure, so not in any file
    bytes: int = 0
    failed: str = ""  # why logging stopped ("" = it did not)
    lost: int = 0  # the loop's ring drops (status.log_lost), filled in by finish()


# Log channels of the shared memory: (meta, ring, slots) field names.
SOURCES = {
    "log": ("log_meta", "log_ring", "log_data"),  # the student's XenoFrtLogger
    "cycle_timing": ("timing_meta", "timing_ring", "timing"),
}  # XRF_LOG_TIMING=1


class HostLogWriter:
    """Drains one log channel of a run (`source`: the logger's ring, or the per-cycle timing
    records) into its file; a thread of the appliance."""

    def __init__(
        self,
        ch: Any,
        identity: dict[str, str],
        run_dir: Path,
        on_alarm: Callable[[str], None] | None = None,
        on_records: Callable[[np.ndarray], None] | None = None,
        timing: bool = True,
        source: str = "log",
        on_note: Callable[[str], None] | None = None,
    ) -> None:
        from .. import channels as chmod

        self._ch = ch
        self._source = source
        self._meta_field, self._ring_field, self._slots_field = SOURCES[source]
        self._lib, self._ffi = chmod.lib, chmod.ffi
        self._identity = identity
        self._run_dir = run_dir
        self._on_alarm = on_alarm
        self._on_note = on_note
        self._on_records = on_records
        self._timing = timing
        self.stats = WriterStats()
        self._fd = -1
        self._size = 0
        self._generation = 0
        self._stride = 0
        self._dtype: np.dtype | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()  # one drain at a time (thread vs finish())
        self._thread: threading.Thread | None = None
        self._last_timing = 0.0
        self._last_hist: dict[str, tuple[int, float]] = {}
        self._count = self._ffi.new("uint32_t *")

    # -- life cycle -------------------------------------------------------------------------

    def start(self) -> None:
        self._thread = threading.Thread(target=self._main, name=f"xrf-{self._source}-writer", daemon=True)
        self._thread.start()

    def finish(self) -> WriterStats:
        """Stop the thread and drain what is left (the loop may be dead: the mapping is ours)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        self.drain(final=True)
        with self._lock:
            if self._fd >= 0:
                try:
                    os.fsync(self._fd)
                except OSError:
                    pass
                os.close(self._fd)
                self._fd = -1
        if self._source != "log":
            self.stats.lost = int(self._ring().dropped)
            return self.stats
        try:
            status = self._ch.status()
            self.stats.lost = int(status.log_lost)
            if not self._host_writes() and self._lib.xrfpy_load_u32(
                self._ffi.addressof(self._ch.shm.log_meta, "ready")
            ):
                self.stats.records = int(status.log_written)  # XRF_LOG_WRITER=process wrote them
        except Exception:  # status locked by a loop that died mid-write: the ring knows too
            self.stats.lost = int(self._ch.shm.log_ring.dropped)
        self._sample_timing(force=True)
        return self.stats

    def _main(self) -> None:
        seen = self._ch.doorbell
        while not self._stop.is_set():
            try:
                self.drain()
                self._sample_timing()
            except Exception:  # never let a bug end logging silently
                log.exception("log writer")
                time.sleep(0.1)
            seen = self._ch.wait_doorbell(seen, WAIT_MS)

    def skip_through(self, last_seq: int) -> int:
        """Release the ring's records numbered <= `last_seq` without writing them: a dead
        appliance wrote them to the file but was killed before it released them (the read
        position lives in shared memory). Call before start(). Returns how many were skipped."""
        import struct

        ring = self._ffi.addressof(self._ch.shm, self._ring_field)
        slots = getattr(self._ch.shm, self._slots_field)
        stride = int(self._ring().slot_size)
        skipped = 0
        while True:
            p = self._lib.xrf_spsc_peek_run(ring, slots, self._count)
            if p == self._ffi.NULL:
                return skipped
            n = int(self._count[0])
            buf = self._ffi.buffer(p, n * stride)
            k = 0
            while k < n and struct.unpack_from("<Q", buf, k * stride)[0] <= last_seq:  # seq: the header's first word
                k += 1
            if k:
                self._lib.xrf_spsc_release_n(ring, k)
                skipped += k
            if k < n:
                return skipped

    def set_on_records(self, fn: Callable[[np.ndarray], None] | None) -> None:
        with self._lock:
            self._on_records = fn

    # -- draining ----------------------------------------------------------------------------

    def _meta(self) -> Any:
        return getattr(self._ch.shm, self._meta_field)

    def _ring(self) -> Any:
        return getattr(self._ch.shm, self._ring_field)

    def _host_writes(self) -> bool:
        m = self._meta()
        if not self._lib.xrfpy_load_u32(self._ffi.addressof(m, "ready")):
            return False
        return int(m.writer) == self._lib.XRF_LOG_WRITER_HOST

    def drain(self, final: bool = False) -> int:
        """Write every ready record; returns how many were taken from the ring."""
        with self._lock:
            if not self._host_writes():
                return 0
            shm = self._ch.shm
            gen = self._lib.xrfpy_load_u64(self._ffi.addressof(self._meta(), "generation"))
            if gen != self._generation:
                self._open_segment(gen)
            taken = 0
            ring = self._ffi.addressof(shm, self._ring_field)
            slots = getattr(shm, self._slots_field)
            while True:
                p = self._lib.xrf_spsc_peek_run(ring, slots, self._count)
                if p == self._ffi.NULL:
                    break
                n = int(self._count[0])
                buf = self._ffi.buffer(p, n * self._stride)
                if self._on_records is not None and self._dtype is not None:
                    # A copy: the slots are reused as soon as they are released.
                    self._on_records(np.frombuffer(bytes(buf), dtype=self._dtype))
                self._write(buf, n)
                self._lib.xrf_spsc_release_n(ring, n)
                taken += n
            return taken

    def _open_segment(self, gen: int) -> None:
        from .reader import make_variables, record_dtype

        m = self._meta()
        self._generation = gen
        self._stride = int(self._ring().slot_size)
        variables = []
        for i in range(min(int(m.nvars), self._lib.XRF_LOG_VARS_MAX)):
            v = m.vars[i]
            variables.append(
                (
                    self._ffi.string(v.name, self._lib.XRF_NAME_MAX).decode("utf-8", "replace"),
                    int(v.type),
                    int(v.offset),
                )
            )
        try:
            vs = make_variables(
                Path("<ring>"),
                [v[0] for v in variables],
                [v[1] for v in variables],
                [v[2] for v in variables],
                ("seq", "cycle", "t_ns"),
            )
            self._dtype = record_dtype(vs, self._stride)
        except Exception:
            self._dtype = None
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
        if self.stats.failed:
            return
        published = self._ffi.string(m.path, self._lib.XRF_PATH_MAX).decode("utf-8", "replace")
        # The loop names the file and is not trusted: the name is confined to the run folder
        # and opened without following symlinks (runfolder.py), whatever the loop published.
        try:
            rel = confine(self._run_dir, published)
        except RunPathError as exc:
            self._fail(f"{exc}: refused, not logged", published)
            return
        path = str(self._run_dir / rel)
        try:
            self._fd = open_in(
                self._run_dir, rel, os.O_WRONLY | os.O_CREAT | os.O_APPEND, int(m.file_mode) or 0o644, create_dirs=True
            )
            self._size = os.fstat(self._fd).st_size
            self._write_all(self.segment_header())
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
        clocks): rt_core's composer with what the loop's writer gives it, the program name, pid and
        cycle frequency from the loop's info block (the program's bytes as they are there) and
        the run's identity (what the loop's environment says: loop_env)."""
        info = self._ch.shm.info
        return logformat.segment_header(
            self._ffi.addressof(self._ch.shm, self._meta_field),
            int(self._ring().slot_size),
            program=self._ffi.string(info.program, self._lib.XRF_NAME_MAX),
            pid=int(info.pid),
            cycle_freq=int(info.cycle_freq),
            start_unix_ns=time.time_ns() if start_unix_ns is None else start_unix_ns,
            start_mono_ns=time.monotonic_ns() if start_mono_ns is None else start_mono_ns,
            project=self._identity.get("project", ""),
            build=self._identity.get("build", ""),
            run=self._identity.get("run", ""),
        )

    def _write_all(self, data: Any) -> None:
        view = memoryview(data)
        while view:
            n = os.write(self._fd, view)
            self._size += n
            view = view[n:]

    def _write(self, buf: Any, n: int) -> None:
        if self._fd < 0:
            self.stats.unwritten += n
            return
        before = self._size
        try:
            self._write_all(buf)
        except OSError as exc:
            # Keep whole records only: the file ends at its last complete record.
            done = (self._size - before) // self._stride
            try:
                os.ftruncate(self._fd, before + done * self._stride)
            except OSError:
                pass
            self.stats.records += done
            self.stats.bytes += done * self._stride
            self.stats.unwritten += n - done
            self._fail(
                f"writing the log file failed ({exc.strerror or exc}) after "
                f"{self.stats.records} records; logging stopped, the run goes on",
                self.stats.files[-1] if self.stats.files else "",
            )
            return
        self.stats.records += n
        self.stats.bytes += n * self._stride

    def _fail(self, message: str, path: str) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
        if not self.stats.failed:
            self.stats.failed = message
            log.error("%s", message)
            if self._on_alarm is not None:
                self._on_alarm(message)

    # -- timing series -----------------------------------------------------------------------

    def _sample_timing(self, force: bool = False) -> None:
        if not self._timing:
            return
        now = time.monotonic()
        if not force and now - self._last_timing < TIMING_PERIOD_S:
            return
        self._last_timing = now
        try:
            hists = self._ch.histograms()
            s = self._ch.status()
        except Exception:
            return
        stages = {}
        for name, h in hists.items():
            prev_n, prev_sum = self._last_hist.get(name, (0, 0.0))
            total = h.mean * h.count
            dn = h.count - prev_n
            stages[name] = {
                "n": dn,
                "mean_ns": round((total - prev_sum) / dn, 1) if dn > 0 else None,
                "p50_ns": h.percentile(50) if h.count else None,
                "p99_ns": h.percentile(99) if h.count else None,
                "max_ns": h.max if h.count else None,
            }
            self._last_hist[name] = (h.count, total)
        line = {
            "t_unix": time.time(),
            "cycles": s.cycles,
            "missed": s.missed,
            "log_written": s.log_written,
            "log_lost": s.log_lost,
            "stages": stages,
        }
        try:
            fd = open_in(self._run_dir, "timing.jsonl", os.O_WRONLY | os.O_CREAT | os.O_APPEND)
            with open(fd, "a", closefd=True) as f:
                f.write(json.dumps(line, separators=(",", ":")) + "\n")
        except OSError:
            pass  # a full disk already raised the log alarm; timing is best effort


# ---- live rerun -----------------------------------------------------------------------------


def _listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


def _free_port(preferred: int) -> int:
    for port in (preferred, 0):
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return s.getsockname()[1]
    raise OSError("no free port")


def _rerun_cli() -> list[str]:
    # The binary itself, not the venv's `rerun` wrapper script: the wrapper runs it as a child, and
    # that child would outlive the appliance (the parent-death signal goes to the wrapper).
    with contextlib.suppress(ImportError):
        import rerun_cli

        exe = Path(rerun_cli.__file__).with_name("rerun")
        if exe.is_file():
            return [str(exe)]
    found = shutil.which("rerun")
    if found:
        return [found]
    return [sys.executable, "-m", "rerun_cli"]


def _spawn_rerun(argv: list[str]) -> subprocess.Popen[bytes]:
    """A rerun server that gets SIGTERM when the appliance dies, a kill -9 included (the atexit
    hook below does not run then), so none is left with parent 1 (server/children.popen_tied)."""
    from ..tied import popen_tied

    return popen_tied(
        argv,
        death_signal=signal.SIGTERM,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )


class _RerunChild:
    """A ``rerun`` child process whose servers listen on 127.0.0.1 only: they have no login of
    their own, so browsers reach them only through the appliance (its /rerun/ files route and its
    gRPC-web read proxy, server/routes_rerun.py). Stopped with the appliance (stop_rerun_children)."""

    def __init__(self, args: list[str], ports: tuple[int, ...], what: str) -> None:
        # Below the appliance (`nice` execs rerun, so every rerun thread inherits it): a live
        # proxy starting with each run must not delay the supervisor's reaction to that run
        # crashing (outputs off within 100 ms).
        nice = ["nice", "-n", str(RERUN_NICE)] if shutil.which("nice") else []
        self.proc = _spawn_rerun([*nice, *_rerun_cli(), *args])
        deadline = time.monotonic() + 20
        while not all(_listening(p) for p in ports):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise OSError(f"the rerun {what} did not start (exit {self.proc.poll()})")
            time.sleep(0.05)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


class RerunViewer(_RerunChild):
    """One per appliance, started on first use: ``rerun --serve-web``, only for the web viewer's
    files (they come from the installed rerun-sdk; nothing from the internet). The appliance
    copies each file once into its data folder and serves it under /rerun/ behind the login.
    Port from XRF_RERUN_WEB_PORT (default 9090; a taken port falls back to a free one)."""

    _instance: RerunViewer | None = None
    _lock = threading.Lock()

    def __init__(self) -> None:
        self.web_port = _free_port(int(os.environ.get("XRF_RERUN_WEB_PORT", "9090")))
        grpc_port = _free_port(0)  # --serve-web always opens a gRPC server too; nothing uses it
        super().__init__(
            [
                "--serve-web",
                "--bind",
                "127.0.0.1",
                "--port",
                str(grpc_port),
                "--web-viewer-port",
                str(self.web_port),
                "--server-memory-limit",
                "1MiB",
            ],
            (self.web_port,),
            "viewer",
        )

    @classmethod
    def get(cls) -> RerunViewer:
        with cls._lock:
            if cls._instance is None or cls._instance.proc.poll() is not None:
                cls._instance = cls()
            return cls._instance


class LiveProxy(_RerunChild):
    """The live stream of ONE run: a ``rerun --serve-grpc`` message proxy on 127.0.0.1 that the
    run's recording (``LiveRerun``) writes to and viewers read from, through the appliance's
    gRPC-web read proxy. One per run, not one per appliance, because a rerun proxy replays
    everything it still buffers to each new viewer: with one shared proxy a student opening the
    live view would receive earlier runs of other students. Opening the next run's proxy stops
    the previous one; the last stays up after its run ends, so its viewers keep their plots.
    Buffer limit XRF_RERUN_MEMORY (default 256MiB: about 8 minutes of 100 Hz × 64 variables)."""

    _current: LiveProxy | None = None
    _lock = threading.Lock()

    def __init__(self, run_id: int, owner: str) -> None:
        self.run_id = run_id
        self.owner = owner
        self.port = _free_port(0)
        super().__init__(
            [
                "--serve-grpc",
                "--bind",
                "127.0.0.1",
                "--port",
                str(self.port),
                "--server-memory-limit",
                os.environ.get("XRF_RERUN_MEMORY", "256MiB"),
            ],
            (self.port,),
            "live proxy",
        )
        self.local_url = f"rerun+http://127.0.0.1:{self.port}/proxy"
        self.read_url = f"http://127.0.0.1:{self.port}"  # where the appliance forwards gRPC-web reads

    @classmethod
    def open_for_run(cls, run_id: int, owner: str) -> LiveProxy:
        with cls._lock:
            if cls._current is not None:
                cls._current.stop()
                cls._current = None
            cls._current = cls(run_id, owner)
            return cls._current

    @classmethod
    def current(cls) -> LiveProxy | None:
        proxy = cls._current
        return proxy if proxy is not None and proxy.proc.poll() is None else None

    @classmethod
    def stop_all(cls) -> None:
        with cls._lock:
            if cls._current is not None:
                cls._current.stop()
                cls._current = None


@atexit.register  # the appliance's normal exit (SIGTERM under systemd) ends them
def stop_rerun_children() -> None:
    """Stop the live proxy and the viewer's file server (also called by the app's shutdown)."""
    LiveProxy.stop_all()
    if RerunViewer._instance is not None:
        RerunViewer._instance.stop()


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

    def __init__(self, proxy: LiveProxy, ch: Any, run_id: int) -> None:
        import rerun as rr

        self._rr = rr
        self._ch = ch
        self._freq = max(1, int(ch.info.get("cycle_freq", 1000)))
        self._every = max(1, int(round(self._freq / LIVE_HZ)))
        self._q: queue.Queue[np.ndarray | None] = queue.Queue(maxsize=256)
        self.dropped = 0
        self._wall_offset = time.time_ns() - time.monotonic_ns()
        self._names: list[str] | None = None
        self._groups: dict[str, list[str]] = {}  # log entity -> its variables (record fields)
        self._series: dict[str, list[str]] = {}  # entity -> the series names logged for it
        self.rec = rr.RecordingStream("xrflab", recording_id=f"run-{run_id}")
        self.rec.connect_grpc(proxy.local_url)
        self._telemetry_reader = ch.telemetry_reader()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._main, name=f"xrf-rerun-{run_id}", daemon=True)
        self._thread.start()

    def feed(self, records: np.ndarray) -> None:
        """From the writer thread: keep every k-th record (by cycle) and queue it; never blocks."""
        if "cycle" not in (records.dtype.names or ()):
            return
        keep = records[records["cycle"] % self._every == 0]
        if len(keep) == 0:
            return
        try:
            self._q.put_nowait(keep)
        except queue.Full:
            self.dropped += len(keep)

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
        names = [n for n in rec.dtype.names or () if n not in ("seq", "cycle", "t_ns")]
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
        samples = self._telemetry_reader.read()
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
            try:
                now = time.monotonic()
                if pending and (done or now - last_records >= SEND_PERIOD_S):
                    last_records = now
                    for batch in _same_dtype_runs(pending):
                        self._send_records(batch)
                    pending.clear()
                if done or now - last_telemetry >= SEND_PERIOD_S:
                    last_telemetry = now
                    self._send_telemetry()
            except Exception:
                pending.clear()
                log.exception("live rerun")
            if done:
                return


def _same_dtype_runs(arrays: list[np.ndarray]) -> list[np.ndarray]:
    """Consecutive arrays of one record layout, concatenated (a new log segment may change it)."""
    return [np.concatenate(list(run)) for _, run in itertools.groupby(arrays, key=lambda a: a.dtype)]


# ---- per run --------------------------------------------------------------------------------


@dataclass
class RunLogging:
    writer: HostLogWriter
    live: LiveRerun | None
    starting: threading.Thread | None = None
    timing: HostLogWriter | None = None  # per-cycle timing records (XRF_LOG_TIMING=1)


def start(
    ch: Any,
    run_id: int,
    run_dir: Path,
    identity: dict[str, str],
    owner: str,
    on_alarm: Callable[[str], None],
    live: bool = True,
    log_timing: bool = False,
    on_note: Callable[[str], None] | None = None,
) -> RunLogging:
    """Start the host writer (and the live rerun stream unless disabled or unavailable; and the
    timing writer when the loop logs its per-cycle timing). `on_note`: a line for the run's
    console (where a log file went)."""
    writer = HostLogWriter(ch, identity, run_dir, on_alarm=on_alarm, on_note=on_note)
    writer.start()
    rl = RunLogging(writer, None)
    if log_timing:
        rl.timing = HostLogWriter(
            ch, identity, run_dir, on_alarm=on_alarm, timing=False, source="cycle_timing", on_note=on_note
        )
        rl.timing.start()
    if live and os.environ.get("XRF_LIVE_RERUN", "1") != "0":
        # rerun's import and servers take a moment on the first run: not on the event loop,
        # and the writer does not wait for them (records before the stream is up are not sent live).
        def connect() -> None:
            try:
                rl.live = LiveRerun(LiveProxy.open_for_run(run_id, owner), ch, run_id)
                writer.set_on_records(rl.live.feed)
            except Exception:
                log.exception("live rerun unavailable")

        rl.starting = threading.Thread(target=connect, name=f"xrf-rerun-start-{run_id}", daemon=True)
        rl.starting.start()
    return rl


def finish(rl: RunLogging) -> WriterStats:
    if rl.timing is not None:
        rl.timing.finish()
    stats = rl.writer.finish()
    if rl.starting is not None:
        rl.starting.join(30.0)
    if rl.live is not None:
        rl.live.close()
    return stats


__all__ = ["HostLogWriter", "LiveProxy", "LiveRerun", "RerunViewer", "RunLogging", "WriterStats", "finish", "start"]


# ---- the loop's environment (appliance/xrflab/server/supervisor.py) --------------------------
# Starting and finishing a run's logging: server/run_logging.py, a run observer (lifecycle.py).


def loop_env(run_id: int, build: str, log_timing: bool = False) -> dict[str, str]:
    """Environment for a run's loop process: the appliance writes the log files (host writer)."""
    env = {"XRF_LOG_WRITER": "host", "XRF_RUN_ID": str(run_id), "XRF_BUILD_ID": build, "XRF_PROJECT": build}
    if log_timing:
        env["XRF_LOG_TIMING"] = "1"
    return env
