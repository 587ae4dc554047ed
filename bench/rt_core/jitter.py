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
   logger, status/histogram publication). Only the cycles in RUN during the slice are counted
   (snapshot after RUN is reached, minus snapshot at the end). By default (`--ours-from cycles`)
   from every cycle's own wake-up - deadline in ns, which the loop records with XRF_LOG_TIMING=1
   (cycle_timing.xrf, written by the loop's helper thread off the loop's CPU; `wakeup_ns`), put
   into cyclictest's buckets by cyclictest's own arithmetic (`ct_us`): so both programs' figures
   come from per-sample values at the same 1 us resolution, and the same samples are also put
   into the loop's own 6 % buckets to show what the resolution alone does (`ours, 6 % buckets`
   in the output). `--ours-from histogram`: from the loop's shared-memory WAKEUP histogram
   (log-linear buckets: 1 ns below 32 ns, then 16 per octave = 6 % wide: 1.0 us at 16-32 us,
   2.0 us at 32-64 us), without the timing log (what sessions 7-10 reported). Both in one run:
   `--ours-from histogram --also-env XRF_LOG_TIMING=1` (rt_core: the loop as it normally runs,
   from its histogram; rt_core': with the timing log, from every cycle at 1 us).
 - cyclictest: `cyclictest -m -p P -a CPU -t 1 -i PERIOD_US -D SECONDS -h 20000 -q`. Its
   histogram (`-h US`, documented as "dump latency histogram to stdout after the run; US is the
   max latency time to be tracked in microseconds") has one line "bucket count" per whole us: a
   sample's latency `(now.s - next.s) * 1e6 + (now.ns - next.ns) / 1000` in C integer arithmetic,
   so bucket i holds [i, i+1) us (one us more for a sample whose second differs from its
   deadline's and whose ns difference is not a whole us: C division truncates towards 0); then
   "# Max Latencies" (us) and "# Histogram Overflows" (samples >= US, not in any bucket).

Percentiles are interpolated linearly inside the bucket that holds them (the samples taken as
spread evenly over the bucket), the same code for both; max is exact for both (ours: see
HistWindow). Ratio = ours / cyclictest; targets p99 <= 1.05 and p99.9 <= 1.5 at every rate, in
the same run. Each of our slices writes its log files into a folder of its own, removed right
after the slice: the kernel's writeback of one slice's log (up to 30 s later) would otherwise land
in some later slice of either program.

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
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from xrflab.logs import open_log  # noqa: E402  (_common put appliance/ on the path)

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


def ct_us(wake_ns: np.ndarray, deadline_ns: np.ndarray) -> np.ndarray:
    """cyclictest's latency of a sample in whole us, from the same two clock readings it uses
    (`calcdiff(now, next)`: seconds times 1e6 plus the ns difference divided by 1000, C integer
    division truncating towards 0)."""
    ds = wake_ns // 1_000_000_000 - deadline_ns // 1_000_000_000
    dns = wake_ns % 1_000_000_000 - deadline_ns % 1_000_000_000
    return ds * 1_000_000 + np.trunc(dns / 1000).astype(np.int64)


def loop_bucket_low(ns: np.ndarray) -> np.ndarray:
    """Lower edge of the rt_core histogram bucket of each value (channels.c: one bucket per ns below
    32 ns, then 16 per power of two); values past the last bucket are not expected here (> 2^35 ns)."""
    ns = np.maximum(ns, 0).astype(np.int64)
    e = np.frexp(np.maximum(ns, 1).astype(np.float64))[1].astype(np.int64) - 1  # floor(log2), exact < 2^53
    shift = np.maximum(e - 4, 0)
    return np.where(ns < 32, ns, (ns >> shift) << shift)


def counts_of(values: np.ndarray) -> tuple[list[int], list[int]]:
    edges, counts = np.unique(values, return_counts=True)
    return [int(x) for x in edges], [int(x) for x in counts]


class OursSlice:
    """One slice of our loop: its WAKEUP histogram window and, with the timing log, every cycle's
    wake-up and deadline (ns) for the same cycles."""

    def __init__(self, wakeup, cycle, missed, wake_ns=None, deadline_ns=None, lost=0):
        self.wakeup = wakeup  # C.HistWindow
        self.cycle = cycle  # C.HistWindow
        self.missed = missed
        self.wake_ns = wake_ns
        self.deadline_ns = deadline_ns
        self.lost = lost  # timing records the loop could not hand to its writer (ring full)


US_WIDTH = lambda e: 1000  # noqa: E731  (cyclictest's buckets, and ours from the timing log)
LOOP_WIDTH = lambda e: C.bucket_high(e) - e  # noqa: E731  (the loop's WAKEUP histogram's buckets)


class OursAcc:
    """One configuration of our loop over a rate's slices: latency (1 us buckets from every cycle,
    or the WAKEUP histogram), the same cycles in the loop's 6 % buckets, the cycle's own work."""

    def __init__(self, name: str, env: dict, per_cycle: bool):
        self.name = name
        self.env = dict(env)
        # Every cycle when asked for (--ours-from cycles) or when this configuration logs its timing
        # anyway (--also-env XRF_LOG_TIMING=1); XRF_LOG_WRITER=host: no helper writes the timing
        # file, so only the histogram is there.
        wants = per_cycle or self.env.get("XRF_LOG_TIMING") == "1"
        self.per_cycle = wants and self.env.get("XRF_LOG_WRITER") != "host"
        self.lat = Merged(US_WIDTH if self.per_cycle else LOOP_WIDTH)
        self.lat6 = Merged(LOOP_WIDTH)
        self.cycle = Merged(LOOP_WIDTH)
        self.lost = 0

    def add(self, sl: OursSlice) -> Merged:
        """Adds a slice; returns the slice's own latency figures."""
        one = Merged(US_WIDTH if self.per_cycle else LOOP_WIDTH)
        if self.per_cycle:
            assert sl.wake_ns is not None and sl.deadline_ns is not None
            lat_ns = sl.wake_ns - sl.deadline_ns
            mx = float(lat_ns.max()) if len(lat_ns) else 0.0
            e, c = counts_of(ct_us(sl.wake_ns, sl.deadline_ns) * 1000)
            self.lat6.add(*counts_of(loop_bucket_low(lat_ns)), mx)
            self.lost += sl.lost
        else:
            e, c, mx = sl.wakeup.edges, sl.wakeup.counts, sl.wakeup.max
        self.lat.add(e, c, mx)
        one.add(e, c, mx)
        self.cycle.add(sl.cycle.edges, sl.cycle.counts, sl.cycle.max)
        self.lat.missed += sl.missed
        return one


def run_ours(
    exe: Path,
    freq: int,
    prio: int,
    cpu: int,
    seconds: float,
    log_root: str,
    idx: int,
    helper_cpu: int | None = None,
    extra_env: dict | None = None,
    per_cycle: bool = True,
) -> OursSlice:
    shm = f"bench_jitter_{os.getpid()}_{idx}"
    # A folder of its own per slice, removed right after it (module docstring).
    log_dir = tempfile.mkdtemp(prefix="slice_", dir=log_root)
    env_extra = {"XRF_MAX_CYCLES": int(freq * (seconds + 30)), **(extra_env or {})}
    if per_cycle:
        env_extra["XRF_LOG_TIMING"] = "1"
    env = C.loop_env(shm, freq, prio, cpu, log_dir, env_extra)
    # --helper-cpu starts the process on that CPU (the loop thread then moves itself to XRF_CPU);
    # the runtime keeps its helper thread off the loop's CPU by itself since issue 30.
    prefix = ["taskset", "-c", str(helper_cpu)] if helper_cpu is not None else None
    try:
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
            loop.stop()  # the helper writes the rest of the timing ring as the loop ends
        out = OursSlice(
            C.HistWindow(h0["wakeup"], h1["wakeup"]), C.HistWindow(h0["cycle"], h1["cycle"]), s1.missed - s0.missed
        )
        if per_cycle:
            log = open_log(Path(log_dir) / "cycle_timing.xrf")
            rec = log.records
            # The cycles counted between the two snapshots: index cycles(s0) .. cycles(s1) - 1.
            sel = rec[(rec["cycle"] >= s0.cycles) & (rec["cycle"] < s1.cycles)]
            wake = sel["t_ns"].astype(np.int64)
            out.wake_ns = wake
            out.deadline_ns = wake - sel["wakeup_ns"].astype(np.int64)
            out.lost = (s1.cycles - s0.cycles) - len(sel)
    finally:
        shutil.rmtree(log_dir, ignore_errors=True)
    return out


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
        "--ours-from",
        choices=("cycles", "histogram"),
        default="cycles",
        help="ours from every cycle's wake-up (XRF_LOG_TIMING=1, cyclictest's 1 us buckets; default) or from the"
        " loop's WAKEUP histogram (6 %% buckets, no timing log)",
    )
    ap.add_argument(
        "--loop-env",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="an extra XRF_* variable for the loop (a diagnosis, e.g. XRF_LOG_WRITER=host: no log file written)",
    )
    ap.add_argument(
        "--also-env",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="also run our loop with this XRF_* variable (on top of --loop-env), as a third program in the same"
        " alternation, reported as rt_core' beside the verdict: e.g. XRF_LOG_WRITER=host (no log file), or, with"
        " --ours-from histogram, XRF_LOG_TIMING=1 (rt_core' then from every cycle at 1 us)",
    )
    a = ap.parse_args()
    extra_env = dict(kv.split("=", 1) for kv in a.loop_env)
    also_env = dict(kv.split("=", 1) for kv in a.also_env)
    if shutil.which("cyclictest") is None:
        print("cyclictest not found: apt-get install rt-tests", file=sys.stderr)
        return 2
    if os.geteuid() != 0:
        print("warning: not root; SCHED_FIFO/mlockall may be refused", file=sys.stderr)

    exe = C.build(C.REPO / "tests/fixtures/loop_probe", Path(a.build_dir))
    log_dir = C.tmpdir("xrf_bench_jitter_")
    per_cycle = a.ours_from == "cycles"
    ct_version = subprocess.run(["cyclictest", "--help"], capture_output=True, text=True).stdout.splitlines()[0]
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"# rt_core wake-up latency vs cyclictest   {datetime.datetime.now().isoformat(timespec='seconds')}")
    print(f"# host {platform.node()} kernel {platform.release()} cpus {os.cpu_count()}; {ct_version}; load {load}")
    if a.helper_cpu is not None:
        print(f"# loop process started with taskset -c {a.helper_cpu}")
    if extra_env:
        print(f"# loop environment also: {' '.join(a.loop_env)}")
    if also_env:
        print(f"# rt_core' is the same loop with also: {' '.join(a.also_env)} (a third program in each slice)")
    print(f"# SCHED_FIFO {a.prio}, CPU {a.cpu}, {a.slices} alternating slices x {a.seconds:g} s per program")
    src = (
        "every cycle's wake-up (XRF_LOG_TIMING=1) in cyclictest's 1 us buckets"
        if per_cycle
        else "WAKEUP histogram (6 % buckets)"
    )
    print(
        f"# ours: {exe.relative_to(C.REPO) if exe.is_relative_to(C.REPO) else exe} in RUN, {src};"
        " cyclictest: its 1 us buckets; percentiles interpolated in the bucket"
    )
    print("# latency = wake-up - the period start it slept until; missed = periods in which no cycle started")
    results = {}
    for freq in [int(x) for x in a.rates.split(",")]:
        progs: list[OursAcc | str] = [OursAcc("rt_core", extra_env, per_cycle), "ct"]
        if also_env:
            progs.append(OursAcc("rt_core'", {**extra_env, **also_env}, per_cycle))
        ct = Merged(US_WIDTH)
        ct_cmd = ""
        for i in range(a.slices):
            order = progs if i % 2 == 0 else progs[::-1]
            slice_notes: list[str] = []
            for who in order:
                if isinstance(who, OursAcc):
                    sl = run_ours(
                        exe, freq, a.prio, a.cpu, a.seconds, log_dir, i, a.helper_cpu, who.env, per_cycle=who.per_cycle
                    )
                    one = who.add(sl)
                    slice_notes.append(
                        f"{who.name} p99 {one.pct(99) / 1000:.1f} p99.9 {one.pct(99.9) / 1000:.1f}"
                        f" max {one.max / 1000:.0f} missed {sl.missed}"
                    )
                else:
                    e, c, mx, ov, miss, ct_cmd = run_cyclictest(freq, a.prio, a.cpu, a.seconds)
                    ct.add(e, c, mx)
                    ct.overflow += ov
                    ct.missed += miss
                    ct.missed_lower_bound |= ov > 0
                    one = Merged(US_WIDTH)
                    one.add(e, c, mx)
                    one.overflow = ov
                    slice_notes.append(
                        f"cyclictest p99 {one.pct(99) / 1000:.1f} p99.9 {one.pct(99.9) / 1000:.1f}"
                        f" max {mx / 1000:.0f} missed {miss}"
                    )
            print(f"#   {freq} Hz slice {i + 1}/{a.slices} (us): " + "; ".join(slice_notes), flush=True)
        results[freq] = ([x for x in progs if isinstance(x, OursAcc)], ct, ct_cmd)

    print()
    print(
        f"{'rate':>8} {'who':<11} {'samples':>9} {'p50 us':>9} {'p99 us':>9} {'p99.9 us':>9} {'max us':>9}"
        f" {'missed':>8}"
    )
    ok = True
    for freq, (ours_list, ct, ct_cmd) in results.items():
        for name, h in [(o.name, o.lat) for o in ours_list] + [("cyclictest", ct)]:
            print(
                f"{freq:>6}Hz {name:<11} {h.count:>9} "
                + " ".join(fmt_us(h.pct(p)) for p in PCTS)
                + " "
                + fmt_us(h.max)
                + f" {h.missed_str():>8}"
            )
        for o in ours_list:
            ours = o.lat
            label = "ratio" if o is ours_list[0] else "ratio'"
            r = {p: ours.pct(p) / ct.pct(p) if ct.pct(p) else float("inf") for p in PCTS}
            rmax = ours.max / ct.max if ct.max else float("inf")
            print(f"{freq:>6}Hz {label:<11} {'':>9} " + " ".join(f"{r[p]:9.2f}" for p in PCTS) + f" {rmax:9.2f}")
            verdicts = []
            for p, limit in TARGETS.items():
                good = r[p] <= limit
                if o is ours_list[0]:  # the verdict is the default configuration's
                    ok &= good
                verdicts.append(f"p{p:g} {r[p]:.2f} (<= {limit:g}) {'PASS' if good else 'FAIL'}")
            print(f"{freq:>6}Hz {o.name} / cyclictest: " + "; ".join(verdicts))
            if o.per_cycle:
                r6 = {p: o.lat6.pct(p) / ct.pct(p) if ct.pct(p) else float("inf") for p in PCTS}
                print(
                    "         resolution check, the same cycles in the loop's 6 % buckets: "
                    + " / ".join(f"p{p:g} {o.lat6.pct(p) / 1000:.2f} us (ratio {r6[p]:.2f})" for p in PCTS)
                )
            else:
                print("         (from the loop's WAKEUP histogram, 6 % buckets)")
            if o.lost:
                print(f"         ({o.lost} cycles had no timing record: the ring was full; not counted)")
            print(
                f"         the loop's own work (CYCLE histogram: wake-up to end of the cycle): p50"
                f" {o.cycle.pct(50) / 1000:.2f} p99.9 {o.cycle.pct(99.9) / 1000:.2f} max {o.cycle.max / 1000:.1f} us"
            )
        print(f"         cyclictest command: {ct_cmd}")
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"# both targets at every rate: {'PASS' if ok else 'FAIL'}; load at the end {load}")
    shutil.rmtree(log_dir, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
