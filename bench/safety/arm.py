"""The arm under every fault, many times, under load: the `hold` safe reaction's figures.

For each fault (segfault, hang, exit(0) in RUN, a STOPPING that never returns; the appliance's
own death is tests/rt_core/test_hold_faults.py's) and --rounds times: a real loop process
(tests/fixtures/arm_faults) raises the youBot arm on the simulated board, the fault takes its
controller away, the safety watcher (rt_core's C thread, as the appliance starts it) holds the
arm, lowers it to its rest stops and zeroes the outputs. Per fault: the first safe output after
the fault (the watcher's safe_ns - event_ns: the ≤ 100 ms / p99 ≤ 20 ms bound), the largest joint
drop (from the mirrored plant state every 2 ms; the tests' bound is 2°) and the time to rest.
With --stress, stress-ng loads every CPU meanwhile (as bench/safety/soak.py does).

    .venv/bin/python bench/safety/arm.py --rounds 5 --stress
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO_ROOT / "appliance"))
sys.path.insert(0, str(REPO_ROOT / "bench" / "appliance"))
sys.path.insert(0, str(REPO_ROOT / "tests"))

from _common import pct  # noqa: E402

from xrf_testing.arm import DROP_BOUND, FAULTS, build_arm, follow, inject, pose, raise_arm, watch  # noqa: E402
from xrf_testing.loops import LoopProcess  # noqa: E402


def one(exe: Path, fault: str, cwd: Path, n: int) -> tuple[float, float, float]:
    """(first safe output ms, largest drop °, time to rest s) of one fault."""
    lp = LoopProcess(exe, f"xrf-arm-bench-{os.getpid()}-{n}", cwd, capture=False, XRF_TRANSPORT="sim", XRF_SIM="youbot")
    try:
        raise_arm(lp)
        w = watch(lp)
        try:
            held = pose(lp.ch)
            t_fault = inject(lp, fault)
            worst, end = follow(w, lp.ch, held, t_fault)
        finally:
            w.stop()
        r = end["result"]
        return (r.safe_ns - r.event_ns) / 1e6, math.degrees(worst), (r.rest_ns - r.event_ns) / 1e9
    finally:
        lp.stop()
        from xrflab.channels import shm_path

        shm_path(lp.shm).unlink(missing_ok=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=5, help="faults of each kind (default 5)")
    ap.add_argument("--stress", action="store_true", help="stress-ng on every CPU meanwhile")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="xrf-arm-bench-") as tmp:
        exe = build_arm(Path(tmp) / "build")
        stress = None
        if args.stress:
            cpus = os.cpu_count() or 1
            stress = subprocess.Popen(["stress-ng", "--cpu", str(cpus), "--quiet"], stdout=subprocess.DEVNULL)
        n = 0
        rows = []
        try:
            for fault in FAULTS:
                safe, drop, rest = [], [], []
                for _ in range(args.rounds):
                    n += 1
                    s, d, r = one(exe, fault, Path(tmp), n)
                    safe.append(s)
                    drop.append(d)
                    rest.append(r)
                rows.append((fault, safe, drop, rest))
        finally:
            if stress is not None:
                stress.terminate()
                stress.wait()
        load = "stress-ng on every CPU" if args.stress else "no added load"
        print(f"\n{args.rounds} faults of each kind, {load}; drop bound {math.degrees(DROP_BOUND):.0f}°\n")
        print("| fault | first safe output p50 / max (ms) | largest drop p50 / max (°) | time to rest p50 / max (s) |")
        print("|---|---|---|---|")
        for fault, safe, drop, rest in rows:
            print(
                f"| {fault} | {pct(safe, 50):.2f} / {max(safe):.2f} | {pct(drop, 50):.2f} / {max(drop):.2f} "
                f"| {pct(rest, 50):.2f} / {max(rest):.2f} |"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
