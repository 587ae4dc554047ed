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
        self._last_hist: dict[str, tuple[int, float]] = {}

    def sample(self, force: bool = False) -> None:
        """A line, when a period has passed since the last one (or `force`: the run's end)."""
        now = time.monotonic()
        if not force and now - self._last < TIMING_PERIOD_S:
            return
        self._last = now
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
            # Through the run folder's helper, the appliance's own file only: a link, a FIFO or a
            # file the loop put in its place is refused (and this sample skipped), never followed.
            fd = open_in(self._run_dir, TIMING_FILE, os.O_WRONLY | os.O_CREAT | os.O_APPEND, own=True)
            with open(fd, "a", closefd=True) as f:
                f.write(json.dumps(line, separators=(",", ":")) + "\n")
        except (OSError, ValueError):
            pass  # a full disk already raised the log alarm; timing is best effort
