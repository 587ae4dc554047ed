#!/usr/bin/env python3
"""What the run sandbox costs the loop: wake-up jitter and cycle time of the same loop, confined
(started by the appliance's launcher, xrflab.guest, exactly as a run) and unconfined (started
directly), in one run.

How: tests/fixtures/loop_probe in RUN state, alternating slices (default 4 x 10 s each, order
flipping every slice: confined, plain, plain, confined, ...) so both see the same background
noise of this shared machine. Jitter = wake time - grid deadline from the loop's own WAKEUP
histogram; cycle = the CYCLE stage histogram (the framework's work per cycle). Ratio =
confined / plain at each percentile (target <= 1.10 at p99). Run as root (SCHED_FIFO).
Not part of the test suite.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from xrflab.channels import Channels  # noqa: E402
from xrflab.server.runs import guest_spawn  # noqa: E402
from xrflab.server.settings import Settings  # noqa: E402

PCTS = (50.0, 99.0, 99.9)


def run_slice(exe: Path, confined: bool, freq: int, prio: int, cpu: int, seconds: float, idx: int):
    tmp = Path(C.tmpdir("xrf-confined-"))
    run_dir = tmp / "run"
    run_dir.mkdir()
    os.chmod(tmp, 0o755)
    env = C.loop_env("x", freq, prio, cpu, str(run_dir), {"XRF_MAX_CYCLES": int(freq * (seconds + 30))})
    if confined:
        spawner = guest_spawn.GuestSpawner(Settings(data_dir=tmp, real_bench=False))
        shm_dir = Path("/dev/shm") / f"xrf-bench-confined-{os.getpid()}-{idx}"
        spawner.prepare_dirs(run_dir, shm_dir)
        genv = {
            k: v
            for k, v in env.items()
            if k in {"XRF_FREQ", "XRF_PRIO", "XRF_CPU", "XRF_QUIET", "XRF_LOG_DIR", "XRF_TRANSPORT", "XRF_MAX_CYCLES"}
        }
        genv.update(PATH="/usr/bin:/bin", XRF_SHM="xrf")
        r, w = os.pipe()
        cfg = spawner.config(exe, run_dir, shm_dir, genv, [exe.parent], w)
        proc = subprocess.Popen(
            guest_spawn.launcher_argv(cfg), pass_fds=(w,), stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT
        )
        os.close(w)
        report = os.read(r, 65536).decode()
        os.close(r)
        shm = f"{shm_dir.name}/xrf"
        if '"error": ""' not in report:
            raise RuntimeError(f"confined start failed: {report}")
    else:
        shm = f"bench_confined_{os.getpid()}_{idx}"
        env["XRF_SHM"] = shm
        proc = subprocess.Popen([str(exe)], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
        shm_dir = None
    loop = C.Loop(proc, Channels.open(shm, wait_s=20), shm)
    try:
        C.go_to_run(loop)
        h0, s0 = loop.ch.histograms(), loop.ch.status()
        time.sleep(seconds)
        h1, s1 = loop.ch.histograms(), loop.ch.status()
    finally:
        loop.stop()
        if shm_dir is not None:
            shutil.rmtree(shm_dir, ignore_errors=True)
        shutil.rmtree(tmp, ignore_errors=True)
    return {k: C.HistWindow(h0[k], h1[k]) for k in ("wakeup", "cycle") if k in h0}, s1.missed - s0.missed


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--freq", type=int, default=1000)
    ap.add_argument("--prio", type=int, default=80)
    ap.add_argument("--cpu", type=int, default=1)
    ap.add_argument("--slices", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=10.0)
    args = ap.parse_args()
    exe = C.build(C.REPO / "tests" / "fixtures" / "loop_probe", Path(C.tmpdir("xrf-confined-build-")))
    results: dict[bool, dict[str, list]] = {True: {}, False: {}}
    misses = {True: 0, False: 0}
    for i in range(args.slices * 2):
        confined = (i % 4) in (0, 3)
        wins, missed = run_slice(exe, confined, args.freq, args.prio, args.cpu, args.seconds, i)
        misses[confined] += missed
        for k, w in wins.items():
            results[confined].setdefault(k, []).append(w)
    print(f"# {args.freq} Hz, prio {args.prio}, CPU {args.cpu}, {args.slices} x {args.seconds:g} s per side")
    for k in ("wakeup", "cycle"):
        for p in PCTS:
            vals = {c: max(w.percentile_mid(p) for w in results[c][k]) for c in (True, False)}
            print(
                f"{k:7s} p{p:<5g} confined {vals[True] / 1000:8.2f} us  plain {vals[False] / 1000:8.2f} us  "
                f"ratio {vals[True] / max(vals[False], 1):.2f}"
            )
        mx = {c: max(w.max for w in results[c][k]) for c in (True, False)}
        print(f"{k:7s} max    confined {mx[True] / 1000:8.2f} us  plain {mx[False] / 1000:8.2f} us")
    print(f"misses  confined {misses[True]}  plain {misses[False]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
