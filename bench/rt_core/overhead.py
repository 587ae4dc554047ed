#!/usr/bin/env python3
"""Framework overhead per cycle of the rt_core loop: instructions (callgrind) and nanoseconds
(stage histograms), for bench/rt_core/overhead_project (cmd + data + monitor + a 16-double
logger active; Xeno2Ros at 100 Hz, monitor.printf at 30 Hz; run() prints and does nothing else).

(a) Instructions, repeatable. The controller runs under
      valgrind --tool=callgrind --collect-atstart=no
               --toggle-collect='XenoFrtRosIcoCore::step()'
               --toggle-collect='xrf::Runtime::endCycle(*)'
    so only the framework's two per-cycle entry points are collected (the loop's own grid
    arithmetic, now() and the sleep syscall in XenoFrtLoop::loop() are outside; ~30 instructions).
    A host follows it (doorbell futex wait + telemetry and monitor reads), commands go
    initialise -> start, and after the loop is in RUN the counters are zeroed
    (callgrind_control -z); after N more cycles they are dumped (callgrind_control -d). In that
    dump, from callgrind_annotate --inclusive=yes:
        framework = incl(XenoFrtRosIcoCore::step) - incl(OverheadBench::run)      [the hook]
                    - incl(sim_xfer)                                             [the wire]
                    + incl(xrf::Runtime::endCycle)
    divided by the number of cycles in the dump = the calls of xrf_data_in_try_read (exactly one
    per step(); counted from the calls= lines of the callgrind file). The monitor print the hook
    asks for (XenoFrtMonitor::printf -> Runtime::monitorWrite -> vsnprintf into the ring, 1 cycle
    in 33) is inside the hook's count; it is shown separately and amortised per cycle.
    Target <= 800 instructions per cycle (issue 30; it was <= 2000 before).

(b) Nanoseconds, noisy. The same controller runs natively (SCHED_FIFO, pinned) in RUN with the
    host following it; the stage histograms (cycles in RUN only, snapshot difference) give mean
    ns of data, cmd, monitor, logger. The status publish (Runtime::endCycle) is in no stage: it
    is timed by endcycle_bench (same project, 1e6 back-to-back calls of the runtime's
    endCycle on a real shared-memory object: hot caches, a lower bound). The fpga stage is the
    sim board's xfer plus IcoIo's framing; the two are not separable from the histograms, so it
    is shown but not added. Compared with XRF2's ~11 us per cycle for this work on a Pi 4
    (thesis: channels 6.5 + logger 3.9 us): different CPU (Cortex-A72 1.5 GHz vs this x86 VM).

Not part of the test suite. Run as root for (b).
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
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

PROJECT = C.HERE / "overhead_project"
TARGET = 800  # framework instructions per cycle (issue 30 item 5)
HOOK = "OverheadBench::run()"
FUNCS = {
    "step": "XenoFrtRosIcoCore::step()",
    "hook": HOOK,
    "sim_xfer": "sim_xfer",
    "endCycle": "xrf::Runtime::endCycle(long, long, long, unsigned long, long)",
    "monitor_print": "XenoFrtMonitor::printf(char const*, ...)",
    "monitorWrite": "xrf::Runtime::monitorWrite(char const*, __va_list_tag*)",
    "update_io": "IcoIo::update_io(IcoIo::IcoWrite const&, IcoIo::IcoRead*)",
    "publishTelemetry": "XenoFrtRosIcoCore::publishTelemetry(int)",
    "applyCommand": "XenoFrtRosIcoCore::applyCommand()",
    "logger": "XenoFrtLogger::log()",
    "state_machine": "FullStateMachine::step()",
    "doorbell_wake": "xrf_doorbell_wake",
    "recordTiming": "xrf::Runtime::recordTiming(long, long, unsigned long)",
}


def annotate_inclusive(path: Path) -> tuple[dict[str, int], int]:
    """Inclusive Ir per function from callgrind_annotate, and the program total.

    callgrind_annotate lists a function once per source file its instructions come from (inlined
    header code gets its own "header.hpp:fn" row, and the same .cpp can appear under an absolute
    and a relative path). Those rows are parts of the function's inclusive cost, and one of them
    covers all of it, so the largest row is taken (checked: step + endCycle = program total).
    Only the function table is read (the annotated-source sections that follow are not)."""
    out = subprocess.run(
        ["callgrind_annotate", "--inclusive=yes", "--threshold=100", str(path)],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    incl: dict[str, int] = {}
    total = 0
    for line in out.splitlines():
        m = re.match(r"^\s*([\d,]+)\s+\([^)]*\)\s+PROGRAM TOTALS", line)
        if m:
            total = int(m.group(1).replace(",", ""))
            continue
        m = re.match(r"^\s*([\d,]+)\s+\([^)]*\)\s+(?:\*\s+)?([^:]*):(.+?)(?:\s+\[[^\]]*\])?$", line)
        if m:
            fn = m.group(3).strip()
            incl[fn] = max(incl.get(fn, 0), int(m.group(1).replace(",", "")))
        elif line.startswith("-- Auto-annotated") or line.startswith("-- User-annotated"):
            break
    return incl, total


def call_counts(path: Path) -> dict[str, int]:
    """Total calls= per callee from a callgrind output file (name compression handled)."""
    names: dict[str, str] = {}
    calls: dict[str, int] = defaultdict(int)
    cfn = None
    for line in path.read_text(errors="replace").splitlines():
        m = re.match(r"^c?fn=\((\d+)\)(?: (.*))?$", line)
        if m:
            if m.group(2):
                names[m.group(1)] = m.group(2)
            if line.startswith("cfn="):
                cfn = names.get(m.group(1))
            continue
        if line.startswith("calls=") and cfn:
            calls[cfn] += int(line[6:].split()[0])
    return calls


def measure_instructions(
    exe: Path,
    cycles: int,
    log_dir: str,
    out_dir: Path,
    extra_toggles: tuple[str, ...] = (),
    extra_env: dict[str, str] | None = None,
) -> dict:
    shm = f"bench_overhead_cg_{os.getpid()}"
    env = C.loop_env(shm, 1000, 0, -1, log_dir)
    env.update(extra_env or {})
    env.pop("XRF_PRIO")
    env.pop("XRF_CPU")
    prefix = [
        "valgrind",
        "--tool=callgrind",
        f"--callgrind-out-file={out_dir}/callgrind.out",
        "--collect-atstart=no",
        "--toggle-collect=XenoFrtRosIcoCore::step()",
        "--toggle-collect=xrf::Runtime::endCycle(*)",
    ] + [f"--toggle-collect={t}" for t in extra_toggles]
    with open(out_dir / "valgrind.log", "w") as vlog:
        loop = C.start_loop(exe, env, shm, cmd_prefix=prefix, stdout=vlog, wait_s=120)
    host = None
    try:
        C.go_to_run(loop, timeout=60)
        host = C.HostReader(loop.ch)
        time.sleep(1.0)
        pid = str(loop.proc.pid)
        subprocess.run(["callgrind_control", "-z", pid], check=True, capture_output=True)
        c0 = loop.ch.status().cycles
        while loop.ch.status().cycles < c0 + cycles:
            time.sleep(0.2)
        subprocess.run(["callgrind_control", "-d", pid], check=True, capture_output=True)
        c1 = loop.ch.status().cycles
        st = loop.ch.status()
    finally:
        if host:
            host.stop()
        loop.stop(timeout=60)
    dumps = sorted(out_dir.glob("callgrind.out.*"), key=lambda p: p.stat().st_mtime)
    dumps = [d for d in dumps if not d.name.endswith(".0") or len(dumps) == 1]
    dump = next(d for d in dumps if re.search(r"\.\d+$", d.name))
    incl, total = annotate_inclusive(dump)
    calls = call_counts(dump)
    got = {k: incl.get(v, 0) for k, v in FUNCS.items()}
    return dict(
        incl=got,
        total=total,
        n=calls.get("xrf_data_in_try_read", 0),
        status_cycles=c1 - c0,
        state=st.state_name,
        dump=dump,
        host=host,
        calls=calls,
    )


def measure_ns(exe: Path, endcycle_exe: Path, seconds: float, prio: int, cpu: int, log_dir: str):
    shm = f"bench_overhead_ns_{os.getpid()}"
    env = C.loop_env(shm, 1000, prio, cpu, log_dir)
    r = C.measure_run_window(exe, env, shm, seconds)
    env2 = C.loop_env(f"bench_endcycle_{os.getpid()}", 1000, prio, cpu, log_dir)
    out = subprocess.run([str(endcycle_exe), "1000000"], env=env2, capture_output=True, text=True, check=True).stdout
    ec = float(re.search(r"endcycle_ns_mean ([\d.]+)", out).group(1))
    try:
        os.unlink(f"/dev/shm/bench_endcycle_{os.getpid()}")
    except OSError:
        pass
    return r.hist, ec, r.cycles, r.missed, r.host


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cycles", type=int, default=20000, help="cycles counted under callgrind")
    ap.add_argument("--seconds", type=float, default=10.0, help="native run for the ns figures")
    ap.add_argument("--prio", type=int, default=80)
    ap.add_argument("--cpu", type=int, default=1)
    ap.add_argument("--build-dir", default="/tmp/xrf_bench/overhead")
    ap.add_argument("--keep", action="store_true", help="keep the callgrind files")
    ap.add_argument(
        "--log-timing",
        action="store_true",
        help="with XRF_LOG_TIMING=1 (per-cycle timing records): its cost is in endCycle",
    )
    a = ap.parse_args()
    for tool in ("valgrind", "callgrind_annotate", "callgrind_control"):
        if shutil.which(tool) is None:
            print(f"{tool} not found (apt-get install valgrind)", file=sys.stderr)
            return 2
    exe = C.build(PROJECT, Path(a.build_dir))
    endcycle_exe = exe.parent / "endcycle_bench"
    log_dir = C.tmpdir("xrf_bench_overhead_")
    out_dir = Path(C.tmpdir("xrf_bench_callgrind_"))
    vg = subprocess.run(["valgrind", "--version"], capture_output=True, text=True).stdout.strip()
    print(f"# rt_core framework overhead per cycle   {datetime.datetime.now().isoformat(timespec='seconds')}")
    print(f"# host {platform.node()} kernel {platform.release()} cpus {os.cpu_count()}; {vg}")
    print(
        "# controller bench/rt_core/overhead_project at 1 kHz: data (Xeno2Ros 100 Hz), cmd, "
        "monitor 30 Hz, logger 16 doubles/cycle; host follows via doorbell"
    )

    extra_env = {"XRF_LOG_TIMING": "1"} if a.log_timing else {}
    if a.log_timing:
        print("# with XRF_LOG_TIMING=1: a timing record per cycle (Runtime::recordTiming, inside endCycle)")
    r = measure_instructions(exe, a.cycles, log_dir, out_dir, extra_env=extra_env)
    i, n = r["incl"], r["n"]
    fw = i["step"] - i["hook"] - i["sim_xfer"] + i["endCycle"]
    print()
    print(
        f"(a) instructions (callgrind Ir, inclusive, {n} cycles in {r['state']}; "
        f"status counted {r['status_cycles']}; host read {r['host'].telemetry} telemetry, "
        f"{r['host'].monitor} monitor lines)"
    )
    print(f"    incl XenoFrtRosIcoCore::step      {i['step']:>12,}  {i['step'] / n:8.1f}/cycle")
    print(f"  - incl {HOOK:<26} {i['hook']:>12,}  {i['hook'] / n:8.1f}/cycle  (hook; holds the monitor print)")
    print(f"  - incl sim_xfer (the wire)          {i['sim_xfer']:>12,}  {i['sim_xfer'] / n:8.1f}/cycle")
    print(f"  + incl xrf::Runtime::endCycle       {i['endCycle']:>12,}  {i['endCycle'] / n:8.1f}/cycle")
    print(f"  = framework                         {fw:>12,}  {fw / n:8.1f}/cycle")
    mp = i["monitor_print"]
    print(
        f"    monitor print asked by the hook   {mp:>12,}  {mp / n:8.1f}/cycle amortised "
        f"(XenoFrtMonitor::printf incl, {r['calls'].get('xrf::Runtime::monitorWrite(char const*, __va_list_tag*)', 0)} lines)"
    )
    print(f"    framework incl. the monitor print {fw + mp:>12,}  {(fw + mp) / n:8.1f}/cycle")
    parts = (
        "update_io",
        "publishTelemetry",
        "applyCommand",
        "logger",
        "state_machine",
        "doorbell_wake",
        "recordTiming",
    )
    # A function inlined into its caller has no row of its own (applyCommand and the state
    # machine's step are inlined into step() since session 6): named, not shown as 0.
    print(
        "    breakdown /cycle: "
        + ", ".join(f"{k} {i[k] / n:.1f}" for k in parts if i[k])
        + "; no row (inlined, or not run): "
        + ", ".join(k for k in parts if not i[k])
    )
    both = i["step"] + i["endCycle"]
    print(
        f"    check: step + endCycle = {both:,} vs callgrind program total {r['total']:,} "
        f"({'equal: only those two were collected' if both == r['total'] else 'DIFFER'})"
    )
    # Cross-check without callgrind_annotate's per-file split: toggles nest, so toggling also on
    # the hook and on sim_xfer switches collection off inside them; the program total is then
    # the framework's count directly.
    out2 = Path(C.tmpdir("xrf_bench_callgrind2_"))
    r2 = measure_instructions(
        exe,
        max(2000, a.cycles // 4),
        log_dir,
        out2,
        extra_toggles=("OverheadBench::run()", "sim_xfer"),
        extra_env=extra_env,
    )
    print(
        f"    cross-check, nested --toggle-collect also on {HOOK} and sim_xfer: program total "
        f"{r2['total']:,} over {r2['n']} cycles = {r2['total'] / r2['n']:.1f}/cycle"
    )
    shutil.rmtree(out2, ignore_errors=True)
    alloc = {
        k: v
        for k, v in r["calls"].items()
        if re.match(r"^(malloc|calloc|realloc|free|posix_memalign|aligned_alloc|operator new|operator delete)\b", k)
    }
    print(
        f"    heap calls in the collected region (step + endCycle, hook and wire included): "
        f"{sum(alloc.values())} {alloc if alloc else ''}"
    )
    verdict = "PASS" if fw / n <= TARGET else "FAIL"
    print(f"    framework instructions per cycle = {fw / n:.0f} (target <= {TARGET}): {verdict}")

    win, ec, cyc, missed, host = measure_ns(exe, endcycle_exe, a.seconds, a.prio, a.cpu, log_dir)
    print()
    print(
        f"(b) nanoseconds (stage histograms, native, SCHED_FIFO {a.prio}, CPU {a.cpu}, {cyc} cycles in RUN,"
        f" {missed} missed)"
    )
    total = 0.0
    for st in ("data", "cmd", "monitor", "logger"):
        w = win[st]
        total += w.mean
        print(f"    {st:<8} mean {w.mean:8.1f} ns  p99 {w.percentile_mid(99):8.0f} ns  max {w.max:8.0f} ns")
    print(f"    status publish (endCycle, endcycle_bench, hot cache) {ec:8.1f} ns")
    total += ec
    print(
        f"    = framework {total:.0f} ns per cycle = {total / 1000:.2f} us "
        f"(XRF2 on a Pi 4: ~11 us for channels + logger; different CPU)"
    )
    for st in ("fpga", "hook", "cycle", "wakeup"):
        w = win[st]
        print(
            f"    [{st}: mean {w.mean:.0f} ns, p99 {w.percentile_mid(99):.0f} ns]"
            + ("  fpga = sim board + IcoIo framing: not separable, not added" if st == "fpga" else "")
        )
    if a.keep:
        print(f"# callgrind files in {out_dir}")
    else:
        shutil.rmtree(out_dir, ignore_errors=True)
    shutil.rmtree(log_dir, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
