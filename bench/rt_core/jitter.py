#!/usr/bin/env python3
"""Wake-up jitter of the rt_core loop against cyclictest, same machine, period, priority, CPU,
in one run.

How: for each rate (1 kHz and 10 kHz by default) the two programs run back-to-back in short
alternating slices (default 4 x 10 s each; the order flips every slice: ours, cyclictest,
cyclictest, ours, ...), so both sample the same background noise of this shared machine without
running at the same time (running them concurrently on one CPU would make each the other's
noise: same SCHED_FIFO priority, one would delay the other's wake-ups).

 - ours: tests/fixtures/loop_probe in RUN state (initialise + start over the command channel, so
   the whole XRF2 cycle runs: FPGA exchange with the simulated board, data, cmd, monitor, hook,
   logger, status/histogram publication). Jitter = wake time - grid deadline, taken from the
   loop's shared-memory WAKEUP histogram (log-linear buckets: 1 ns below 32 ns, then 16 per
   octave = 6 % resolution). Only the cycles in RUN during the slice are counted (histogram
   snapshot after RUN is reached, minus snapshot at the end of the slice).
 - cyclictest: `cyclictest -m -p P -a CPU -t 1 -i PERIOD_US -D SECONDS -h MAXUS -q`; its
   histogram has 1 us buckets (latency truncated to whole us). Same definition: wake - expected.

Percentiles are given as the middle of the bucket that holds them (ours: the 6 % bucket;
cyclictest: [i, i+1) us -> i + 0.5 us), so neither side gains from its quantisation; max is exact
for both (ours: see HistWindow). Ratio = ours / cyclictest at p99 (target <= 1.10).

Run as root (SCHED_FIFO, mlockall). Not part of the test suite.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

PCTS = (50.0, 99.0, 99.9)


class Merged:
    """Histogram (ns edges, counts) merged over slices; percentiles as bucket middles."""

    def __init__(self, width_fn):
        self.b: dict[int, int] = {}
        self.max = 0.0
        self.width_fn = width_fn
        self.overflow = 0

    def add(self, edges, counts, mx):
        for e, n in zip(edges, counts):
            self.b[e] = self.b.get(e, 0) + n
        self.max = max(self.max, mx)

    @property
    def count(self):
        return sum(self.b.values()) + self.overflow

    def pct(self, p):
        rank = p / 100.0 * self.count
        seen = 0
        for e in sorted(self.b):
            seen += self.b[e]
            if seen >= rank and seen > 0:
                return e + self.width_fn(e) / 2.0
        return self.max  # in cyclictest's overflow


def run_ours(
    exe: Path, freq: int, prio: int, cpu: int, seconds: float, log_dir: str, idx: int, helper_cpu: int | None = None
):
    shm = f"bench_jitter_{os.getpid()}_{idx}"
    env = C.loop_env(shm, freq, prio, cpu, log_dir, {"XRF_MAX_CYCLES": int(freq * (seconds + 30))})
    # The runtime starts its in-band helper thread before it pins the loop thread, so the helper
    # inherits the process's affinity; --helper-cpu starts the process on that CPU (the loop
    # thread then moves itself to XRF_CPU), keeping the helper off the loop's CPU.
    prefix = ["taskset", "-c", str(helper_cpu)] if helper_cpu is not None else None
    loop = C.start_loop(exe, env, shm, cmd_prefix=prefix)
    try:
        C.go_to_run(loop)
        h0 = loop.ch.histograms()["wakeup"]
        s0 = loop.ch.status()
        time.sleep(seconds)
        h1 = loop.ch.histograms()["wakeup"]
        s1 = loop.ch.status()
        if loop.ch.status().state_name != "RUN":
            raise RuntimeError("loop left RUN during the slice")
    finally:
        loop.stop()
    w = C.HistWindow(h0, h1)
    return w, s1.missed - s0.missed


def run_cyclictest(freq: int, prio: int, cpu: int, seconds: float):
    period_us = int(round(1e6 / freq))
    argv = [
        "cyclictest",
        "-m",
        "-p",
        str(prio),
        "-a",
        str(cpu),
        "-t",
        "1",
        "-i",
        str(period_us),
        "-D",
        f"{int(seconds)}",
        "-h",
        "20000",
        "-q",
    ]
    out = subprocess.run(argv, capture_output=True, text=True, check=True).stdout
    edges, counts = [], []
    mx = 0
    overflow = 0
    for line in out.splitlines():
        m = re.match(r"^(\d+) (\d+)$", line)
        if m:
            n = int(m.group(2))
            if n:
                edges.append(int(m.group(1)) * 1000)
                counts.append(n)
            continue
        m = re.match(r"^# Max Latencies: (\d+)", line)
        if m:
            mx = int(m.group(1)) * 1000
        m = re.match(r"^# Histogram Overflows: (\d+)", line)
        if m:
            overflow = int(m.group(1))
    return edges, counts, mx, overflow, " ".join(argv)


def fmt_us(ns):
    return f"{ns / 1000:9.2f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rates", default="1000,10000", help="loop rates in Hz (comma separated)")
    ap.add_argument("--slices", type=int, default=4, help="alternating slices per program and rate")
    ap.add_argument("--seconds", type=float, default=10.0, help="length of one slice")
    ap.add_argument("--prio", type=int, default=80)
    ap.add_argument("--cpu", type=int, default=1)
    ap.add_argument("--build-dir", default="/tmp/xrf_bench/loop_probe")
    ap.add_argument(
        "--helper-cpu",
        type=int,
        default=None,
        help="start the loop process on this CPU so its in-band helper thread stays off --cpu",
    )
    a = ap.parse_args()
    if shutil.which("cyclictest") is None:
        print("cyclictest not found: apt-get install rt-tests", file=sys.stderr)
        return 2
    if os.geteuid() != 0:
        print("warning: not root; SCHED_FIFO/mlockall may be refused", file=sys.stderr)

    exe = C.build(C.REPO / "tests/fixtures/loop_probe", Path(a.build_dir))
    log_dir = C.tmpdir("xrf_bench_jitter_")
    ct_version = subprocess.run(["cyclictest", "--help"], capture_output=True, text=True).stdout.splitlines()[0]
    print(f"# rt_core wake-up jitter vs cyclictest   {datetime.datetime.now().isoformat(timespec='seconds')}")
    print(f"# host {platform.node()} kernel {platform.release()} cpus {os.cpu_count()}; {ct_version}")
    if a.helper_cpu is not None:
        print(f"# loop process started with taskset -c {a.helper_cpu}: its helper thread runs on CPU {a.helper_cpu}")
    print(f"# SCHED_FIFO {a.prio}, CPU {a.cpu}, {a.slices} alternating slices x {a.seconds:g} s per program")
    print(
        f"# ours: {exe.relative_to(C.REPO) if exe.is_relative_to(C.REPO) else exe} in RUN, WAKEUP histogram"
        " (6 % buckets); cyclictest: 1 us buckets; percentiles = bucket middles"
    )
    results = {}
    for freq in [int(x) for x in a.rates.split(",")]:
        ours = Merged(lambda e: C.bucket_high(e) - e)
        ct = Merged(lambda e: 1000)
        missed = 0
        ct_cmd = ""
        for i in range(a.slices):
            order = ("ours", "ct") if i % 2 == 0 else ("ct", "ours")
            slice_notes: list[str] = []
            for who in order:
                if who == "ours":
                    w, miss = run_ours(exe, freq, a.prio, a.cpu, a.seconds, log_dir, i, a.helper_cpu)
                    ours.add(w.edges, w.counts, w.max)
                    missed += miss
                    one = Merged(lambda e: C.bucket_high(e) - e)
                    one.add(w.edges, w.counts, w.max)
                    slice_notes.append(f"ours p99 {one.pct(99) / 1000:.1f} max {w.max / 1000:.0f}")
                else:
                    e, c, mx, ov, ct_cmd = run_cyclictest(freq, a.prio, a.cpu, a.seconds)
                    ct.add(e, c, mx)
                    ct.overflow += ov
                    one = Merged(lambda e: 1000)
                    one.add(e, c, mx)
                    slice_notes.append(f"cyclictest p99 {one.pct(99) / 1000:.1f} max {mx / 1000:.0f}")
            print(f"#   {freq} Hz slice {i + 1}/{a.slices} (us): " + "; ".join(slice_notes), flush=True)
        results[freq] = (ours, ct, missed, ct_cmd)

    print()
    print(f"{'rate':>8} {'who':<11} {'samples':>9} {'p50 us':>9} {'p99 us':>9} {'p99.9 us':>9} {'max us':>9}")
    for freq, (ours, ct, missed, ct_cmd) in results.items():
        for name, h in (("rt_core", ours), ("cyclictest", ct)):
            print(
                f"{freq:>6}Hz {name:<11} {h.count:>9} " + " ".join(fmt_us(h.pct(p)) for p in PCTS) + " " + fmt_us(h.max)
            )
        r = {p: ours.pct(p) / ct.pct(p) if ct.pct(p) else float("inf") for p in PCTS}
        rmax = ours.max / ct.max if ct.max else float("inf")
        print(f"{freq:>6}Hz {'ratio':<11} {'':>9} " + " ".join(f"{r[p]:9.2f}" for p in PCTS) + f" {rmax:9.2f}")
        verdict = "PASS" if r[99.0] <= 1.10 else "FAIL"
        print(
            f"{freq:>6}Hz ratio ours/cyclictest at p99 = {r[99.0]:.2f} (target <= 1.10): {verdict};"
            f" rt_core missed cycles {missed}; cyclictest overflows (>20 ms) {ct.overflow}"
        )
        print(f"         cyclictest command: {ct_cmd}")
    shutil.rmtree(log_dir, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
