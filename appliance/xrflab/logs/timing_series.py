"""A run's timing series: the framework's stage histograms, sampled once a second.

Issue 4 item 2, without an rt_core change: the loop keeps cumulative histograms of its cycle
stages (wake-up jitter included) in the shared memory; they are sampled once per second (in the
appliance by the supervisor's timing task, elsewhere by the host writer's thread) into
``timing.jsonl`` in the run folder, the lines written at the host writer's drains: per stage the interval's count and mean, and the
cumulative p50/p99/max, with the run's cycle, miss and log counters. Best effort: a sample that
cannot be read or written is skipped (a full disk has raised the log alarm already).
"""

from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..channels.names import STAGE_NAMES
from ..channels.status import stage_figures_many, timing_words_of
from ..runfolder import open_in

if TYPE_CHECKING:
    from ..channels import Channels
    from ..channels.binding import CData

TIMING_PERIOD_S = 1.0
MAX_PENDING = 64  # samples taken and not written at most (a writer that stopped writing them)
TIMING_FILE = "timing.jsonl"


class TimingSeries:
    """The run's timing.jsonl. A sample is taken (`take`: one status copy, its counters and the
    histograms' words kept) once a second, and its line made and written by `write_pending`, at
    once (`sample`) or for several samples together: in the appliance the event loop's
    once-a-second timing task takes them and the host writer's thread writes them at its drains,
    every few seconds, so that thread does not wake once a second for them (issue 30 item 4,
    session 13: the line's thread wake-up was a third of the idle appliance's CPU). Thread-safe:
    take, write_pending and sample may be called from different threads."""

    def __init__(self, ch: Channels, run_dir: Path) -> None:
        self._ch = ch
        self._run_dir = run_dir
        self._last = 0.0
        self._last_hist: dict[str, tuple[int, int]] = {}
        self._fd = -1  # timing.jsonl, opened once (close())
        self._lock = threading.Lock()  # the pending samples, _last, _closed
        self._write_lock = threading.Lock()  # the lines: _last_hist and the file, one writer at a time
        self._pending: list[tuple[float, dict[str, int], np.ndarray]] = []  # taken, not written
        self.taken = 0  # samples taken (tests)
        self._closed = False  # the run's end: its last line is written

    def take(self, force: bool = False, copy: CData | None = None) -> bool:
        """Take a sample when a period has passed since the last one (or `force`: the run's end);
        its line is written by the next write_pending. True when one was taken. `copy`: a status
        copy the caller made just now (Channels.status_copy), taken instead of a copy of its own."""
        now = time.monotonic()
        with self._lock:
            if self._closed:
                return False
            # (A wait for due_in() may end a hair early: within a millisecond counts as due.)
            if not force and now - self._last < TIMING_PERIOD_S - 0.001:
                return False
            self._last = now
            try:
                # One copy of the status block, its histograms kept as words (the figures of
                # several samples are made together: write_pending).
                counters, words = self._ch.timing_words() if copy is None else timing_words_of(copy)
            except Exception:
                return False
            if len(self._pending) < MAX_PENDING:  # bounded should nobody write them
                self._pending.append((time.time(), counters, words))
                self.taken += 1
            return True

    def write_pending(self) -> None:
        """The lines of the samples taken and not written yet, in order, in one write."""
        # Two locks: take (the event loop, once a second) only waits for the list's hand-over,
        # never for the figures and the write of the samples before it.
        with self._write_lock:
            with self._lock:
                pending, self._pending = self._pending, []
                if not pending or self._closed:
                    return
            out = []
            # The figures of every pending sample in one pass (stage_figures_many).
            every = stage_figures_many(np.stack([words for _, _, words in pending]), (50.0, 99.0))
            for (t_unix, counters, _), sample_figures in zip(pending, every):
                figures = dict(zip(STAGE_NAMES, sample_figures))
                stages = {}
                for name, f in figures.items():
                    prev_n, prev_sum = self._last_hist.get(name, (0, 0))
                    dn = f.count - prev_n
                    stages[name] = {
                        "n": dn,
                        "mean_ns": round((f.sum_ns - prev_sum) / dn, 1) if dn > 0 else None,
                        "p50_ns": f.percentiles[0] if f.count else None,
                        "p99_ns": f.percentiles[1] if f.count else None,
                        "max_ns": f.max_ns if f.count else None,
                    }
                    self._last_hist[name] = (f.count, f.sum_ns)
                line = {"t_unix": t_unix, **counters, "stages": stages}
                out.append(json.dumps(line, separators=(",", ":")) + "\n")
            self._append("".join(out).encode())

    def sample(self, force: bool = False) -> None:
        """A line, when a period has passed since the last one (or `force`: the run's end),
        taken and written at once."""
        if self.take(force):
            self.write_pending()

    def due_in(self) -> float:
        """Seconds until the next sample is due."""
        return max(0.0, self._last + TIMING_PERIOD_S - time.monotonic())

    def _append(self, data: bytes) -> None:
        try:
            if self._fd < 0:
                # Through the run folder's helper, the appliance's own file only: a link, a FIFO or
                # a file the loop put in its place is refused (and this sample skipped), never
                # followed. Opened once and kept: what a loop does to the name afterwards cannot
                # point the appliance's writes anywhere else.
                self._fd = open_in(self._run_dir, TIMING_FILE, os.O_WRONLY | os.O_CREAT | os.O_APPEND, own=True)
            view = memoryview(data)
            while view:
                view = view[os.write(self._fd, view) :]
        except (OSError, ValueError):
            self._close_fd()  # a full disk already raised the log alarm; timing is best effort: next line reopens

    def close(self) -> None:
        """The run's end (after its last line): nothing is taken or written from then on."""
        with self._write_lock:
            with self._lock:
                self._closed = True
            self._close_fd()

    def _close_fd(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
