"""Shared bits of the appliance benchmarks: a real appliance (the test harness's launcher:
uvicorn in its own process, real loop processes) and percentile helpers."""

from __future__ import annotations

import os
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO_ROOT / "appliance"))
sys.path.insert(0, str(REPO_ROOT / "tests"))  # the test helpers: xrf_testing

from xrf_testing.harness import Server, shared_builds_root, start_server, stop_server  # noqa: E402


@contextmanager
def appliance(**settings: Any) -> Iterator[Server]:
    with tempfile.TemporaryDirectory(prefix="xrf-bench-") as data:
        server = start_server(Path(data), shared_builds_root(), **settings)
        try:
            yield server
        finally:
            stop_server(server)


def pct(values: list[float], p: float) -> float:
    """Nearest-rank percentile."""
    if not values:
        return float("nan")
    ordered = sorted(values)
    rank = max(1, min(len(ordered), round(p / 100 * len(ordered) + 0.5)))
    return ordered[rank - 1]


def summary_ms(values_ns: list[int]) -> str:
    ms = [v / 1e6 for v in values_ns]
    return (
        f"n={len(ms)}  p50={pct(ms, 50):.3f} ms  p99={pct(ms, 99):.3f} ms  "
        f"max={max(ms):.3f} ms  mean={sum(ms) / len(ms):.3f} ms"
    )


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process (and its reaped children are not included)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    return (int(fields[11]) + int(fields[12])) / ticks
