"""The arm under every fault, many times, under load: the `hold` safe reaction's figures.

For each fault (segfault, hang, exit(0) in RUN, a STOPPING that never returns; the appliance's
own death is tests/server/test_appliance_kill_hold.py's) and --rounds times: a real loop process
(tests/fixtures/arm_faults) raises the youBot arm on the simulated board, the fault takes its
controller away, the safety watcher (rt_core's C thread, as the appliance starts it) holds the
arm, lowers it to its rest stops and zeroes the outputs. Per fault: the first safe output after
the fault (the watcher's safe_ns - event_ns: the ≤ 100 ms / p99 ≤ 20 ms bound), the largest joint
drop (from the mirrored plant state every 2 ms; the tests' bound is 2°) and the time to rest.
With --stress, stress-ng loads every CPU meanwhile (as bench/safety/soak.py does). With
--appliance N, the whole appliance is also killed N times during the youBot example's RUN (the
per-run xrf-watch puts the arm down; the restarted appliance reads its record): the figures of
tests/server/test_appliance_kill_hold.py, N times.

    .venv/bin/python bench/safety/arm.py --rounds 5 --stress
    .venv/bin/python bench/safety/arm.py --rounds 20 --stress --appliance 5
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO_ROOT / "appliance"))
sys.path.insert(0, str(REPO_ROOT / "bench" / "appliance"))
sys.path.insert(0, str(REPO_ROOT / "tests"))

from _common import pct  # noqa: E402

from xrf_testing.arm import (  # noqa: E402
    DROP_BOUND,
    FAULTS,
    build_arm,
    comm,
    follow,
    follow_until_ended,
    inject,
    pose,
    raise_arm,
    raise_example,
    watch,
)
from xrf_testing.harness import (  # noqa: E402
    UNCONFINED_UNLESS_ROOT,
    Server,
    shared_builds_root,
    start_server,
    stop_server,
    wait_for,
)
from xrf_testing.leaks import descendants  # noqa: E402
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


def closed(server: Server, run_id: int) -> dict:
    """The run record once the (restarted) appliance has closed it."""
    return wait_for(lambda: (r := server.http.get(f"/api/runs/{run_id}").json())["end_reason"] and r, 40)


def appliance_kills(rounds: int, data: Path, out: list[tuple[float, float, float]]) -> None:
    """The whole appliance killed `rounds` times (tests/server/test_appliance_kill_hold.py's
    fault, measured): the real appliance runs the youBot example with the arm raised in RUN, is
    killed with SIGKILL, its run's xrf-watch puts the arm down; the next appliance (same data
    folder and port) closes the orphaned run with xrf-watch's record and runs the next round.
    Per round (first safe output ms and time to rest s from the record, largest drop ° followed
    from the segment) into `out`."""
    server = start_server(data, shared_builds_root(), allow_unconfined=UNCONFINED_UNLESS_ROOT)
    try:
        for _ in range(rounds):
            run, ch = raise_example(server)
            try:
                held = pose(ch)
                watcher = next(p for p in descendants(server.proc.pid) if comm(p) == "xrf-watch")
                t_fault = time.monotonic()
                os.kill(server.proc.pid, signal.SIGKILL)
                server.proc.wait()
                worst = follow_until_ended(ch, held, t_fault, watcher)
                port = int(server.url.rsplit(":", 1)[1])
                server = start_server(data, shared_builds_root(), allow_unconfined=UNCONFINED_UNLESS_ROOT, port=port)
                row = closed(server, run["id"])
            finally:
                ch.close()
            o = row["safe_outcome"]
            assert row["end_reason"] == "appliance_gone" and o and o["phase"] == "rest", row
            out.append((o["safe_ms"], math.degrees(worst), o["rest_s"]))
    finally:
        stop_server(server)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=5, help="faults of each kind (default 5)")
    ap.add_argument("--stress", action="store_true", help="stress-ng on every CPU meanwhile")
    ap.add_argument(
        "--appliance", type=int, default=0, metavar="N", help="also kill the whole appliance N times (~25 s each)"
    )
    args = ap.parse_args()
    load_before = os.getloadavg()  # the machine may be shared: the figures say how busy it was
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
            if args.appliance:
                kills: list[tuple[float, float, float]] = []
                appliance_kills(args.appliance, Path(tmp) / "appliance", kills)
                rows.append(("appliance_kill9", *(list(col) for col in zip(*kills, strict=True))))
        finally:
            if stress is not None:
                stress.terminate()
                stress.wait()
        load = "stress-ng on every CPU" if args.stress else "no added load"
        before, after = (", ".join(f"{x:.2f}" for x in la) for la in (load_before, os.getloadavg()))
        print(f"\n{' '.join(['bench/safety/arm.py', *sys.argv[1:]])} (uid {os.geteuid()}, {os.cpu_count()} CPUs)")
        print(f"load average before {before}, after {after} (1, 5, 15 min)")
        kinds = f"{args.rounds} faults of each kind" + (f", {args.appliance} appliance kills" if args.appliance else "")
        print(f"{kinds}, {load}; drop bound {math.degrees(DROP_BOUND):.0f}°\n")
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
