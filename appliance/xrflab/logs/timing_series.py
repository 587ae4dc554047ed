"""A run's timing series: the framework's stage histograms, sampled once a second.

Issue 4 item 2, without an rt_core change: the loop keeps cumulative histograms of its cycle
stages (wake-up jitter included) in the shared memory; the host writer samples them once per
second into ``timing.jsonl`` in the run folder: per stage the interval's count and mean, and the
cumulative p50/p99/max, with the run's cycle, miss and log counters. Best effort: a sample that
cannot be read or written is skipped (a full disk has raised the log alarm already).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

from ..runfolder import open_in

if TYPE_CHECKING:
    from ..channels import Channels

TIMING_PERIOD_S = 1.0
TIMING_FILE = "timing.jsonl"


class TimingSeries:
    def __init__(self, ch: Channels, run_dir: Path) -> None:
        self._ch = ch
        self._run_dir = run_dir
        self._last = 0.0
        self._last_hist: dict[str, tuple[int, int]] = {}
        self._fd = -1  # timing.jsonl, opened once (close())

    def sample(self, force: bool = False) -> None:
        """A line, when a period has passed since the last one (or `force`: the run's end)."""
        now = time.monotonic()
        # (A wait for due_in() may end a hair early: within a millisecond counts as due.)
        if not force and now - self._last < TIMING_PERIOD_S - 0.001:
            return
        self._last = now
        try:
            # One copy of the status block, the stages' figures from it without a Histogram per
            # stage (issue 30 item 4: this line was most of the host writer's CPU, idle).
            counters, figures = self._ch.timing_figures((50.0, 99.0))
        except Exception:
            return
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
        line = {"t_unix": time.time(), **counters, "stages": stages}
        self._append((json.dumps(line, separators=(",", ":")) + "\n").encode())

    def due_in(self) -> float:
        """Seconds until the next line is due (the host writer's thread sleeps until then or
        its next drain, whichever comes first)."""
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
            self.close()  # a full disk already raised the log alarm; timing is best effort: next line reopens

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
