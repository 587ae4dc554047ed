"""Where a process's Python memory grows: tracemalloc snapshots taken on a signal (for the
benchmarks that look for growth, bench/appliance/practical.py --tracemalloc).

The test harness's appliance (serve_for_test.py) calls `install` when $XRF_TRACEMALLOC names a
folder. The first SIGUSR2 starts tracing (not the start: tracing the appliance's imports makes
its start several times slower, past the harness's 20 s, and what was allocated before the first
round is not what grows) and writes the first snapshot; each later one writes the next
(snapshot-000.tracemalloc, -001, ...: written under a temporary name and renamed, so a reader
waiting for the file never reads half of one). `growth` compares two snapshots by the
lines that allocated the memory still held. Tracing costs the traced process CPU time and memory
of its own: figures taken with it are for finding what grows, not for the footprint.
"""

from __future__ import annotations

import os
import signal
import tracemalloc
from pathlib import Path
from types import FrameType

ENV = "XRF_TRACEMALLOC"
FRAMES = 10  # frames kept per allocation: enough to get from a library's line to our caller
# tracemalloc's own bookkeeping and the import machinery's: not the program's growth.
IGNORED = (tracemalloc.__file__, "<frozen importlib._bootstrap>", "<frozen importlib._bootstrap_external>")


def install(folder: Path, frames: int = FRAMES, sig: int = signal.SIGUSR2) -> None:
    """At each `sig`, trace allocations from then on (the first) and write a snapshot into
    `folder` (the handler runs in the main thread, between two bytecodes of whatever it ran)."""
    folder.mkdir(parents=True, exist_ok=True)
    taken = [0]

    def dump(_signum: int, _frame: FrameType | None) -> None:
        if not tracemalloc.is_tracing():
            tracemalloc.start(frames)
        snap = tracemalloc.take_snapshot().filter_traces([tracemalloc.Filter(False, f) for f in IGNORED])
        final = folder / f"snapshot-{taken[0]:03d}.tracemalloc"
        part = final.with_suffix(".part")
        snap.dump(str(part))
        os.replace(part, final)
        taken[0] += 1

    signal.signal(sig, dump)


def snapshot_path(folder: Path, n: int) -> Path:
    """The n-th snapshot's file (0 the first)."""
    return folder / f"snapshot-{n:03d}.tracemalloc"


def growth(before: Path, after: Path, n: int = 15, key: str = "lineno") -> list[str]:
    """The n places whose held memory grew most from `before` to `after`: one line each, the
    difference in KiB and in blocks, the file:line (and with key="traceback", its callers)."""
    a = tracemalloc.Snapshot.load(str(before))
    b = tracemalloc.Snapshot.load(str(after))
    stats = [s for s in b.compare_to(a, key) if s.size_diff > 0][:n]
    out = []
    for s in stats:
        where = s.traceback.format(limit=4 if key == "traceback" else 1, most_recent_first=True)
        out.append(
            f"{s.size_diff / 1024:+.1f} KiB ({s.count_diff:+d} blocks, {s.size / 1024:.1f} KiB held): "
            + " <- ".join(w.strip() for w in where if not w.startswith("    "))
        )
    return out
