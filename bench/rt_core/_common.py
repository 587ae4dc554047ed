"""Shared helpers for the rt_core benchmarks (not a test module; imported by the scripts here).

Everything here is host-side: it builds a controller with xrflab.build, starts it with the XRF_*
environment, drives it to RUN through the command channel and reads the shared-memory
histograms. Nothing is added to rt_core.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(REPO / "appliance"))

from xrflab.build import build_project  # noqa: E402
from xrflab.channels import Channels  # noqa: E402


def build(project: Path, build_dir: Path) -> Path:
    """Build a controller project quietly, from scratch (a kept CMake cache would keep pointing at
    an older rt_core install whose shared-memory layout the Python side no longer speaks)."""
    import shutil

    shutil.rmtree(build_dir, ignore_errors=True)
    lines: list[str] = []
    res = build_project(project, build_dir=build_dir, log=lines.append)
    return Path(res.executable)


def loop_env(shm: str, freq: int, prio: int, cpu: int, log_dir: str, extra: dict | None = None) -> dict:
    env = dict(os.environ)
    env.update(
        XRF_SHM=shm,
        XRF_FREQ=str(freq),
        XRF_PRIO=str(prio),
        XRF_CPU=str(cpu),
        XRF_QUIET="1",
        XRF_LOG_DIR=log_dir,
        XRF_TRANSPORT="sim",
    )
    if extra:
        env.update({k: str(v) for k, v in extra.items()})
    return env


@dataclass
class Loop:
    proc: subprocess.Popen
    ch: Channels
    shm: str

    def stop(self, timeout: float = 10.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            rc = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            rc = self.proc.wait()
        try:
            self.ch.close()
        except Exception:
            pass
        try:
            os.unlink(f"/dev/shm/{self.shm}")
        except OSError:
            pass
        return rc


def start_loop(
    exe: Path, env: dict, shm: str, cmd_prefix: list[str] | None = None, stdout=subprocess.DEVNULL, wait_s: float = 20.0
) -> Loop:
    argv = (cmd_prefix or []) + [str(exe)]
    proc = subprocess.Popen(argv, env=env, stdout=stdout, stderr=subprocess.STDOUT)
    try:
        ch = Channels.open(shm, wait_s=wait_s)
    except BaseException:
        proc.kill()
        proc.wait()
        try:
            os.unlink(f"/dev/shm/{shm}")
        except OSError:
            pass
        raise
    return Loop(proc, ch, shm)


def go_to_run(loop: Loop, timeout: float = 10.0) -> None:
    """initialise then start, as a host would; raises if the loop refuses."""
    for cmd in ("initialise", "start"):
        res = loop.ch.wait_command(loop.ch.send_command(cmd), timeout=timeout)
        if not res.accepted:
            raise RuntimeError(f"{cmd} rejected: {res}")
    deadline = time.monotonic() + timeout
    while loop.ch.status().state_name.upper() not in ("RUN", "RUNNING"):
        if time.monotonic() > deadline:
            raise RuntimeError(f"loop not in RUN: {loop.ch.status().state_name}")
        time.sleep(0.01)


class HistWindow:
    """The part of a shared-memory histogram accumulated between two snapshots.

    Bucket counts subtract exactly. min/max do not: the window's max is exact when the
    process-wide max rose during the window, otherwise it is the upper edge of the highest
    non-empty bucket of the window (flagged `max_exact=False`).
    """

    def __init__(self, before, after):
        b = dict(zip(before.edges, before.counts))
        self.edges: list[int] = []
        self.counts: list[int] = []
        for e, n in zip(after.edges, after.counts):
            d = n - b.get(e, 0)
            if d > 0:
                self.edges.append(e)
                self.counts.append(d)
        self.count = sum(self.counts)
        self.sum_ns = after.mean * after.count - before.mean * before.count
        self.mean = self.sum_ns / self.count if self.count else 0.0
        if after.max > before.max:
            self.max, self.max_exact = float(after.max), True
        else:
            self.max, self.max_exact = float(bucket_high(self.edges[-1])) if self.edges else 0.0, False

    def percentile_mid(self, p: float) -> float:
        """Middle (ns) of the log-linear bucket holding the p-th percentile."""
        rank = p / 100.0 * self.count
        seen = 0
        for e, n in zip(self.edges, self.counts):
            seen += n
            if seen >= rank and seen > 0:
                return (e + bucket_high(e)) / 2.0
        return self.max


def bucket_high(low: int) -> int:
    """Upper edge of the rt_core histogram bucket whose lower edge is `low` (channels.c:
    one bucket per ns below 32 ns, then 16 sub-buckets per power of two, ~6 %)."""
    if low < 32:
        return low + 1
    e = low.bit_length() - 1
    return low + (1 << (e - 4))


def tmpdir(prefix: str) -> str:
    return tempfile.mkdtemp(prefix=prefix)


class HostReader:
    """A host that follows the loop like the appliance does: waits on the doorbell (futex) and
    drains telemetry and monitor rings, in a background thread. Counts what it read."""

    def __init__(self, ch: Channels):
        import threading

        self.ch = ch
        self.telemetry = 0
        self.monitor = 0
        self.wakeups = 0
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()

    def _run(self):
        tr = self.ch.telemetry_reader()
        mr = self.ch.monitor_reader()
        seen = 0
        while not self._stop.is_set():
            seen = self.ch.wait_doorbell(seen, 100)
            self.wakeups += 1
            self.telemetry += len(tr.read())
            self.monitor += len(mr.read())

    def stop(self):
        self._stop.set()
        self._t.join(2.0)


@dataclass
class RunWindow:
    """What a loop in RUN gathered between two snapshots: stage histograms and counters."""

    hist: dict[str, HistWindow]
    cycles: int
    missed: int
    log_lost: int
    host: HostReader


def measure_run_window(exe: Path, env: dict, shm: str, seconds: float) -> RunWindow:
    """Start the loop, drive it to RUN with a host following it (HostReader), settle 0.5 s, and
    return the difference of two snapshots `seconds` apart: RUN cycles only."""
    loop = start_loop(exe, env, shm)
    host = None
    try:
        go_to_run(loop)
        host = HostReader(loop.ch)
        time.sleep(0.5)
        h0, s0 = loop.ch.histograms(), loop.ch.status()
        time.sleep(seconds)
        h1, s1 = loop.ch.histograms(), loop.ch.status()
    finally:
        if host:
            host.stop()
        loop.stop()
    return RunWindow(
        {k: HistWindow(h0[k], h1[k]) for k in h1},
        s1.cycles - s0.cycles,
        s1.missed - s0.missed,
        s1.log_lost - s0.log_lost,
        host,
    )
