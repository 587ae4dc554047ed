"""Helper of syscalls.sh: runs the overhead controller under `strace -f -ttt`, drives it to RUN,
follows it as a host (doorbell + telemetry), and writes the window of steady state.

Usage: python3 _syscalls_run.py EXE TRACE_FILE SECONDS FREQ PRIO CPU
Prints shell-style lines: LOOP_TID, T_STEADY, T_END (epoch seconds, same clock as strace -ttt),
CYCLES (cycles in the window), TELEMETRY/MONITOR/WAKEUPS (read by the host), STATE.
"""

from __future__ import annotations

import os
import shutil
import signal
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402


def fifo_threads(pid: int) -> list[int]:
    out = []
    for tid in os.listdir(f"/proc/{pid}/task"):
        stat = Path(f"/proc/{pid}/task/{tid}/stat").read_text()
        fields = stat[stat.rindex(")") + 2 :].split()
        policy = int(fields[38])  # field 41 of stat; fields start at field 3
        if policy in (1, 2):  # SCHED_FIFO, SCHED_RR
            out.append(int(tid))
    return out


def main() -> int:
    exe, trace, seconds, freq, prio, cpu = sys.argv[1:7]
    shm = f"bench_syscalls_{os.getpid()}"
    log_dir = C.tmpdir("xrf_bench_syscalls_")
    env = C.loop_env(shm, int(freq), int(prio), int(cpu), log_dir)
    prefix = ["strace", "-f", "-ttt", "-qq", "-o", trace]
    loop = C.start_loop(Path(exe), env, shm, cmd_prefix=prefix, wait_s=30)
    host = None
    pid = 0
    try:
        C.go_to_run(loop, timeout=30)
        host = C.HostReader(loop.ch)
        time.sleep(1.0)  # steady state: the first RUN cycles and the host's attach are behind us
        # strace's pid is loop.proc.pid; the controller is its child.
        kids = Path(f"/proc/{loop.proc.pid}/task/{loop.proc.pid}/children").read_text().split()
        pid = int(kids[0])
        tids = fifo_threads(pid)
        c0 = loop.ch.status().cycles
        t0 = time.time()
        # SECONDS x FREQ cycles run, not SECONDS: under strace the loop misses periods (each traced
        # call costs tens of us), and since issue 30 a missed period is skipped, not run late.
        target = c0 + int(float(seconds) * int(freq))
        give_up = time.monotonic() + 3 * float(seconds)
        while loop.ch.status().cycles < target and time.monotonic() < give_up:
            time.sleep(0.05)  # polling the loop's cycle count
        t1 = time.time()
        st = loop.ch.status()
        c1 = st.cycles
    finally:
        if host:
            host.stop()
        # The controller itself first: a SIGTERM to strace (loop.stop) detaches it and leaves the
        # controller running, reparented, with /dev/cpu_dma_latency held (seen 2026-11-27).
        if pid:
            try:
                os.kill(pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
        loop.stop(timeout=30)
        shutil.rmtree(log_dir, ignore_errors=True)
    print(f"PID={pid}")
    print(f"LOOP_TID={tids[0] if len(tids) == 1 else ','.join(map(str, tids))}")
    print(f"T_STEADY={t0:.6f}")
    print(f"T_END={t1:.6f}")
    print(f"CYCLES={c1 - c0}")
    print(f"MISSED={st.missed}")
    print(f"STATE={st.state_name}")
    print(f"TELEMETRY={host.telemetry}")
    print(f"MONITOR={host.monitor}")
    print(f"WAKEUPS={host.wakeups}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
