#!/usr/bin/env python3
"""Wake-up latency of the rt_core loop against cyclictest, same machine, period, priority, CPU,
in one run, with the same definitions for both.

How: for each rate (1 kHz and 10 kHz by default) the two programs run back-to-back in short
alternating slices (default 4 x 10 s each; the order flips every slice: ours, cyclictest,
cyclictest, ours, ...), so both sample the same background noise of this shared machine without
running at the same time (running them concurrently on one CPU would make each the other's
noise: same SCHED_FIFO priority, one would delay the other's wake-ups). Both run at the same
SCHED_FIFO priority on the same CPU with their memory locked and /dev/cpu_dma_latency held at 0.

The same two figures for both programs:
 - latency of a cycle = its wake-up time - the start of the period it asked to wake at (the
   deadline it slept until). One sample per cycle that ran.
 - missed periods = grid periods in which no cycle started, because the previous cycle woke or
   ended after the period had begun: both skip to the next period boundary (the loop's policy
   after an overrun, docs/rt_core/runtime.md; cyclictest's `while (now > next) next += interval`)
   and neither runs a late period. Ours: the loop's status counter `missed`. cyclictest does not
   print it; a sample of latency L skipped floor(L / T) periods (its histogram's 1 us buckets
   give that exactly for a whole-us period), and an overflow (> 20 ms) at least 20 ms / T.

 - ours: tests/fixtures/loop_probe in RUN state (initialise + start over the command channel, so
   the whole XRF2 cycle runs: FPGA exchange with the simulated board, data, cmd, monitor, hook,
   logger, status/histogram publication), from the loop's shared-memory WAKEUP histogram
   (log-linear buckets: 1 ns below 32 ns, then 16 per octave = 6 % wide). Only the cycles in RUN
   during the slice are counted (snapshot after RUN is reached, minus snapshot at the end).
 - cyclictest: `cyclictest -m -p P -a CPU -t 1 -i PERIOD_US -D SECONDS -h 20000 -q`; its
   histogram has 1 us buckets (the latency truncated to whole us: bucket i holds [i, i+1) us).

Percentiles are interpolated linearly inside the bucket that holds them (the samples taken as
spread evenly over the bucket), for both, so neither side gains or loses from its quantisation
(a bucket middle would move ours by up to 3 %, too coarse for a 5 % target); max is exact for
both (ours: see HistWindow). Ratio = ours / cyclictest; targets p99 <= 1.05 and p99.9 <= 1.5 at
every rate, in the same run.

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
TARGETS = {99.0: 1.05, 99.9: 1.5}
CT_HIST_US = 20000  # cyclictest -h: 1 us buckets up to here, then "overflows"


class Merged:
    """Histogram (ns lower edges, counts) merged over slices; percentiles interpolated in the
    bucket; missed periods added up beside it."""

    def __init__(self, width_fn):
        self.b: dict[int, int] = {}
        self.max = 0.0
        self.width_fn = width_fn
        self.overflow = 0
        self.missed = 0
        self.missed_lower_bound = False  # some missed periods are only known as "at least"

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
            n = self.b[e]
            if n and seen + n >= rank:
                v = e + (rank - seen) / n * self.width_fn(e)
                return min(v, self.max) if self.max else v
            seen += n
        return self.max  # in cyclictest's overflow

    def missed_str(self):
        return ("≥" if self.missed_lower_bound else "") + str(self.missed)


def run_ours(
    exe: Path,
    freq: int,
    prio: int,
    cpu: int,
    seconds: float,
    log_dir: str,
    idx: int,
    helper_cpu: int | None = None,
    extra_env: dict | None = None,
):
    shm = f"bench_jitter_{os.getpid()}_{idx}"
    env = C.loop_env(shm, freq, prio, cpu, log_dir, {"XRF_MAX_CYCLES": int(freq * (seconds + 30)), **(extra_env or {})})
    # --helper-cpu starts the process on that CPU (the loop thread then moves itself to XRF_CPU);
    # the runtime keeps its helper thread off the loop's CPU by itself since issue 30.
    prefix = ["taskset", "-c", str(helper_cpu)] if helper_cpu is not None else None
    loop = C.start_loop(exe, env, shm, cmd_prefix=prefix)
    try:
        C.go_to_run(loop)
        h0 = loop.ch.histograms()
        s0 = loop.ch.status()
        time.sleep(seconds)  # the point: the slice's length of cycles
        h1 = loop.ch.histograms()
        s1 = loop.ch.status()
        if loop.ch.status().state_name != "RUN":
            raise RuntimeError("loop left RUN during the slice")
    finally:
        loop.stop()
    return C.HistWindow(h0["wakeup"], h1["wakeup"]), C.HistWindow(h0["cycle"], h1["cycle"]), s1.missed - s0.missed


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
        str(CT_HIST_US),
        "-q",
    ]
    out = subprocess.run(argv, capture_output=True, text=True, check=True).stdout
    edges, counts = [], []
    mx = 0
    overflow = 0
    missed = 0
    for line in out.splitlines():
        m = re.match(r"^(\d+) (\d+)$", line)
        if m:
            n = int(m.group(2))
            if n:
                us = int(m.group(1))
                edges.append(us * 1000)
                counts.append(n)
                # A wake-up L us late passed over the periods that began before it: floor(L / T)
                # (L lies in [us, us + 1), T is whole us, so the floor of us / T is exact).
                missed += n * (us // period_us)
            continue
        m = re.match(r"^# Max Latencies: (\d+)", line)
        if m:
            mx = int(m.group(1)) * 1000
        m = re.match(r"^# Histogram Overflows: (\d+)", line)
        if m:
            overflow = int(m.group(1))
    missed += overflow * (CT_HIST_US // period_us)  # at least; an overflow's own latency is not printed
    return edges, counts, mx, overflow, missed, " ".join(argv)


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
        help="start the loop process on this CPU (the runtime keeps its helper thread off --cpu anyway)",
    )
    ap.add_argument(
        "--loop-env",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="an extra XRF_* variable for the loop (a diagnosis, e.g. XRF_LOG_WRITER=host: no log file written)",
    )
    a = ap.parse_args()
    extra_env = dict(kv.split("=", 1) for kv in a.loop_env)
    if shutil.which("cyclictest") is None:
        print("cyclictest not found: apt-get install rt-tests", file=sys.stderr)
        return 2
    if os.geteuid() != 0:
        print("warning: not root; SCHED_FIFO/mlockall may be refused", file=sys.stderr)

    exe = C.build(C.REPO / "tests/fixtures/loop_probe", Path(a.build_dir))
    log_dir = C.tmpdir("xrf_bench_jitter_")
    ct_version = subprocess.run(["cyclictest", "--help"], capture_output=True, text=True).stdout.splitlines()[0]
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"# rt_core wake-up latency vs cyclictest   {datetime.datetime.now().isoformat(timespec='seconds')}")
    print(f"# host {platform.node()} kernel {platform.release()} cpus {os.cpu_count()}; {ct_version}; load {load}")
    if a.helper_cpu is not None:
        print(f"# loop process started with taskset -c {a.helper_cpu}")
    if extra_env:
        print(f"# loop environment also: {' '.join(a.loop_env)}")
    print(f"# SCHED_FIFO {a.prio}, CPU {a.cpu}, {a.slices} alternating slices x {a.seconds:g} s per program")
    print(
        f"# ours: {exe.relative_to(C.REPO) if exe.is_relative_to(C.REPO) else exe} in RUN, WAKEUP histogram"
        " (6 % buckets); cyclictest: 1 us buckets; percentiles interpolated in the bucket"
    )
    print("# latency = wake-up - the period start it slept until; missed = periods in which no cycle started")
    results = {}
    for freq in [int(x) for x in a.rates.split(",")]:
        ours = Merged(lambda e: C.bucket_high(e) - e)
        ours_cycle = Merged(lambda e: C.bucket_high(e) - e)
        ct = Merged(lambda e: 1000)
        ct_cmd = ""
        for i in range(a.slices):
            order = ("ours", "ct") if i % 2 == 0 else ("ct", "ours")
            slice_notes: list[str] = []
            for who in order:
                if who == "ours":
                    w, cyc, miss = run_ours(exe, freq, a.prio, a.cpu, a.seconds, log_dir, i, a.helper_cpu, extra_env)
                    ours.add(w.edges, w.counts, w.max)
                    ours_cycle.add(cyc.edges, cyc.counts, cyc.max)
                    ours.missed += miss
                    one = Merged(lambda e: C.bucket_high(e) - e)
                    one.add(w.edges, w.counts, w.max)
                    slice_notes.append(
                        f"ours p99 {one.pct(99) / 1000:.1f} p99.9 {one.pct(99.9) / 1000:.1f}"
                        f" max {w.max / 1000:.0f} missed {miss}"
                    )
                else:
                    e, c, mx, ov, miss, ct_cmd = run_cyclictest(freq, a.prio, a.cpu, a.seconds)
                    ct.add(e, c, mx)
                    ct.overflow += ov
                    ct.missed += miss
                    ct.missed_lower_bound |= ov > 0
                    one = Merged(lambda e: 1000)
                    one.add(e, c, mx)
                    one.overflow = ov
                    slice_notes.append(
                        f"cyclictest p99 {one.pct(99) / 1000:.1f} p99.9 {one.pct(99.9) / 1000:.1f}"
                        f" max {mx / 1000:.0f} missed {miss}"
                    )
            print(f"#   {freq} Hz slice {i + 1}/{a.slices} (us): " + "; ".join(slice_notes), flush=True)
        results[freq] = (ours, ours_cycle, ct, ct_cmd)

    print()
    print(
        f"{'rate':>8} {'who':<11} {'samples':>9} {'p50 us':>9} {'p99 us':>9} {'p99.9 us':>9} {'max us':>9}"
        f" {'missed':>8}"
    )
    ok = True
    for freq, (ours, ours_cycle, ct, ct_cmd) in results.items():
        for name, h in (("rt_core", ours), ("cyclictest", ct)):
            print(
                f"{freq:>6}Hz {name:<11} {h.count:>9} "
                + " ".join(fmt_us(h.pct(p)) for p in PCTS)
                + " "
                + fmt_us(h.max)
                + f" {h.missed_str():>8}"
            )
        r = {p: ours.pct(p) / ct.pct(p) if ct.pct(p) else float("inf") for p in PCTS}
        rmax = ours.max / ct.max if ct.max else float("inf")
        print(f"{freq:>6}Hz {'ratio':<11} {'':>9} " + " ".join(f"{r[p]:9.2f}" for p in PCTS) + f" {rmax:9.2f}")
        verdicts = []
        for p, limit in TARGETS.items():
            good = r[p] <= limit
            ok &= good
            verdicts.append(f"p{p:g} {r[p]:.2f} (<= {limit:g}) {'PASS' if good else 'FAIL'}")
        print(f"{freq:>6}Hz ratio ours/cyclictest: " + "; ".join(verdicts))
        print(
            f"         the loop's own work (CYCLE histogram: wake-up to end of the cycle): p50"
            f" {ours_cycle.pct(50) / 1000:.2f} p99.9 {ours_cycle.pct(99.9) / 1000:.2f} max {ours_cycle.max / 1000:.1f} us"
        )
        print(f"         cyclictest command: {ct_cmd}")
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"# both targets at every rate: {'PASS' if ok else 'FAIL'}; load at the end {load}")
    shutil.rmtree(log_dir, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
