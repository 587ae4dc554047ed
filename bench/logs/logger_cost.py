#!/usr/bin/env python3
"""Logger cost in the loop per record: instructions (callgrind) and nanoseconds (the loop's
"logger" stage histogram), for 16 and 64 logged doubles (bench/logs/logger_cost_project, N from
XRF_BENCH_NVARS). The file is written off the loop either way (in-band helper thread or the
appliance); what is measured is the loop side: XenoFrtLogger::log() = sequence number, ring slot
reservation (xrf_spsc_begin: one acquire load of the consumer's tail), the slot header
(seq, cycle, t_ns), memcpy of the record, and the release store of the head.

(a) Instructions, repeatable: the controller runs under
        valgrind --tool=callgrind --collect-atstart=no --toggle-collect='XenoFrtLogger::log()'
    (bench/rt_core/overhead.py's approach: collection only inside the measured function), is
    driven to RUN, the counters are zeroed (callgrind_control -z), N cycles later dumped
    (callgrind_control -d). Instructions per record = the dump's program total / the calls of
    xrf_spsc_begin (exactly one per log(), counted from the dump's calls= lines).
(b) Nanoseconds, noisy: the same controller natively (SCHED_FIFO, pinned), the "logger" stage
    histogram over a window of cycles in RUN (snapshot difference). The stage is logger.log() plus
    one clock read (rt_core/src/xrf2_rosico.cpp); the "cmd" stage with no command pending (a ring
    poll plus one clock read) is printed beside it as a reference for that floor.

Not part of the test suite. Run as root for (b). XRF2 on a Pi 4 spent 3.9 us per cycle on its
logger, writing through an EVL proxy (thesis).
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "rt_core"))
import _common as C  # noqa: E402
from overhead import annotate_inclusive, call_counts  # noqa: E402

PROJECT = HERE / "logger_cost_project"
LOG_FN = "XenoFrtLogger::log()"


def instructions(exe: Path, nvars: int, cycles: int, out_dir: Path) -> dict:
    shm = f"bench_logger_cg_{os.getpid()}_{nvars}"
    env = C.loop_env(shm, 1000, 0, -1, C.tmpdir("xrf_bench_logger_"), {"XRF_BENCH_NVARS": nvars})
    env.pop("XRF_PRIO")
    env.pop("XRF_CPU")
    prefix = [
        "valgrind",
        "--tool=callgrind",
        f"--callgrind-out-file={out_dir}/callgrind.out",
        "--collect-atstart=no",
        f"--toggle-collect={LOG_FN}",
    ]
    with open(out_dir / "valgrind.log", "w") as vlog:
        loop = C.start_loop(exe, env, shm, cmd_prefix=prefix, stdout=vlog, wait_s=120)
    try:
        C.go_to_run(loop, timeout=60)
        time.sleep(1.0)
        pid = str(loop.proc.pid)
        subprocess.run(["callgrind_control", "-z", pid], check=True, capture_output=True)
        c0 = loop.ch.status().cycles
        while loop.ch.status().cycles < c0 + cycles:
            time.sleep(0.2)
        subprocess.run(["callgrind_control", "-d", pid], check=True, capture_output=True)
        lost = loop.ch.status().log_lost
    finally:
        loop.stop(timeout=60)
    dumps = [d for d in out_dir.glob("callgrind.out.*") if d.name.split(".")[-1].isdigit()]
    dump = max(dumps, key=lambda p: p.stat().st_mtime)
    incl, total = annotate_inclusive(dump)
    calls = call_counts(dump)
    n = calls.get("xrf_spsc_begin", 0)
    return {
        "total": total,
        "n": n,
        "per": total / n if n else float("nan"),
        "log_incl": incl.get(LOG_FN, 0),
        "memcpy": sum(v for k, v in incl.items() if "memcpy" in k or "memmove" in k),
        "lost": lost,
    }


def nanoseconds(exe: Path, nvars: int, seconds: float, prio: int, cpu: int, freq: int) -> dict:
    shm = f"bench_logger_ns_{os.getpid()}_{nvars}"
    env = C.loop_env(shm, freq, prio, cpu, C.tmpdir("xrf_bench_logger_"), {"XRF_BENCH_NVARS": nvars})
    r = C.measure_run_window(exe, env, shm, seconds)
    w, ref = r.hist["logger"], r.hist["cmd"]
    return {
        "cmd_mean": ref.mean,
        "mean": w.mean,
        "p50": w.percentile_mid(50),
        "p99": w.percentile_mid(99),
        "max": w.max,
        "count": w.count,
        "cycles": r.cycles,
        "missed": r.missed,
        "lost": r.log_lost,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--vars", default="16,64", help="numbers of doubles to measure (comma separated)")
    ap.add_argument("--cycles", type=int, default=20000, help="cycles counted under callgrind")
    ap.add_argument("--seconds", type=float, default=10.0, help="native run for the ns figures")
    ap.add_argument("--freq", type=int, default=1000)
    ap.add_argument("--prio", type=int, default=80)
    ap.add_argument("--cpu", type=int, default=1)
    ap.add_argument("--build-dir", default="/tmp/xrf_bench/logger_cost")
    a = ap.parse_args()
    for tool in ("valgrind", "callgrind_annotate", "callgrind_control"):
        if shutil.which(tool) is None:
            print(f"{tool} not found (apt-get install valgrind)", file=sys.stderr)
            return 2
    exe = C.build(PROJECT, Path(a.build_dir))
    vg = subprocess.run(["valgrind", "--version"], capture_output=True, text=True).stdout.strip()
    print(f"# logger cost per record in the loop   {datetime.datetime.now().isoformat(timespec='seconds')}")
    print(f"# host {platform.node()} kernel {platform.release()} cpus {os.cpu_count()}; {vg}")
    print("# controller bench/logs/logger_cost_project: N doubles logged every cycle, nothing else")
    for nvars in [int(x) for x in a.vars.split(",")]:
        out_dir = Path(C.tmpdir("xrf_bench_logger_cg_"))
        r = instructions(exe, nvars, a.cycles, out_dir)
        ns = nanoseconds(exe, nvars, a.seconds, a.prio, a.cpu, a.freq)
        shutil.rmtree(out_dir, ignore_errors=True)
        print()
        print(f"{nvars} doubles ({nvars * 8} B payload + 24 B header per record)")
        print(
            f"  (a) instructions per record  {r['per']:8.1f}   ({r['total']:,} Ir over {r['n']} records under "
            f"callgrind; memcpy share {r['memcpy'] / max(r['n'], 1):.1f}/record)"
        )
        print(
            f"  (b) ns per record (logger stage, native, SCHED_FIFO {a.prio}, CPU {a.cpu}, {a.freq} Hz): "
            f"mean {ns['mean']:.1f}  p50 {ns['p50']:.0f}  p99 {ns['p99']:.0f}  max {ns['max']:.0f}  "
            f"over {ns['count']} cycles, {ns['missed']} missed, {ns['lost']} records lost"
        )
        print(
            f"      reference: the cmd stage with no command pending (one clock read + an empty ring poll) "
            f"mean {ns['cmd_mean']:.1f} ns; every stage includes one clock read"
        )
    print()
    print("XRF2 on a Pi 4: 3.9 us per cycle for its logger (thesis); different CPU, see README.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
