#!/bin/sh
# Proof that the rt_core loop thread makes no system call in steady state apart from its sleep
# (clock_nanosleep) and the doorbell (futex wake of a waiting host).
#
# How: the overhead benchmark controller (bench/rt_core/overhead_project: data, cmd, monitor,
# 16-double logger) runs under `strace -f -ttt` from its first instruction, SCHED_FIFO and pinned.
# A host drives it to RUN (initialise, start) and follows it like the appliance does (futex wait
# on the doorbell, reads telemetry and monitor lines), so the doorbell really rings. After 1 s in
# RUN the host notes the time (steady state begins), waits until SECONDS x FREQ cycles have run
# (default 12 000; at most 3 x SECONDS), notes the time again and stops the loop. The trace is split by the -ttt timestamps:
# set-up (before steady state), steady state (the window), teardown (after; not shown). Each part
# is a per-thread histogram of system calls; the loop thread is the SCHED_FIFO one (read from
# /proc/PID/task/*/stat, it is the main thread: loop() runs on the thread that calls it).
#
# Usage: sudo bench/rt_core/syscalls.sh [SECONDS] [FREQ_HZ]      (not part of the test suite)
set -eu
SECONDS_=${1:-12}
FREQ=${2:-1000}
PRIO=${XRF_BENCH_PRIO:-80}
CPU=${XRF_BENCH_CPU:-1}
HERE=$(cd "$(dirname "$0")" && pwd)
REPO=$(cd "$HERE/../.." && pwd)
BUILD=${XRF_BENCH_BUILD:-/tmp/xrf_bench/overhead}
WORK=$(mktemp -d /tmp/xrf_bench_strace.XXXXXX)
trap 'rm -rf "$WORK"' EXIT

command -v strace >/dev/null || { echo "strace not found: apt-get install strace" >&2; exit 2; }
EXE=$(cd "$REPO" && python3 -c "
import sys; sys.path.insert(0, 'bench/rt_core'); import _common as C
print(C.build(C.HERE / 'overhead_project', '$BUILD'))")

echo "# rt_core loop-thread system calls   $(date -Is)"
echo "# host $(uname -n) kernel $(uname -r) cpus $(nproc); $(strace -V | head -1)"
echo "# $EXE at $FREQ Hz, SCHED_FIFO $PRIO, CPU $CPU, traced by: strace -f -ttt -qq -o TRACE EXE"
python3 "$HERE/_syscalls_run.py" "$EXE" "$WORK/trace" "$SECONDS_" "$FREQ" "$PRIO" "$CPU" > "$WORK/run.env"
. "$WORK/run.env"
echo "# loop pid $PID, loop thread (SCHED_FIFO) tid $LOOP_TID; steady window $T_STEADY .. $T_END;"
echo "# $CYCLES cycles in the window in state $STATE ($MISSED missed in the whole run); host read"
echo "# $TELEMETRY telemetry records and $MONITOR monitor lines over $WAKEUPS doorbell waits"

# strace -f -o FILE lines: "TID EPOCH.usec syscall(args) = ret" (also "<... resumed>" halves,
# counted once at their start, and "+++ exited" / "--- SIG" lines, skipped).
histogram() { # $1 = awk condition on the time t
  awk -v loop="$LOOP_TID" -v ts="$T_STEADY" -v te="$T_END" "
    \$3 ~ /^[a-z_0-9]+\\(/ {
      t = \$2 + 0; tid = \$1; name = \$3; sub(/\\(.*/, \"\", name);
      if ($1) { n[tid \" \" name]++; tot[tid]++ }
    }
    END {
      for (k in n) { split(k, a, \" \"); printf \"  %-8s %-10s %-22s %8d\\n\", a[1], (a[1] == loop ? \"loop\" : \"other\"), a[2], n[k] }
    }" "$WORK/trace" | sort -k1,1n -k4,4nr
}
echo
echo "set-up (start of the process .. steady state), per thread:   tid  thread  syscall  count"
histogram "t < ts"
echo
echo "steady state ($CYCLES cycles), per thread:   tid  thread  syscall  count"
histogram "t >= ts && t <= te" | tee "$WORK/steady.txt"

OTHER=$(awk -v loop="$LOOP_TID" '$1 == loop && $3 != "clock_nanosleep" && $3 != "futex" {s += $4} END {print s + 0}' "$WORK/steady.txt")
SLEEPS=$(awk -v loop="$LOOP_TID" '$1 == loop && $3 == "clock_nanosleep" {print $4}' "$WORK/steady.txt")
FUTEX=$(awk -v loop="$LOOP_TID" '$1 == loop && $3 == "futex" {print $4}' "$WORK/steady.txt")
# Futex calls of the loop thread must all be wakes (the doorbell), never waits.
FUTEX_NOT_WAKE=$(awk -v loop="$LOOP_TID" -v ts="$T_STEADY" -v te="$T_END" \
  '$1 == loop && $2 >= ts && $2 <= te && $3 ~ /^futex\(/ && $0 !~ /FUTEX_WAKE/ {n++} END {print n + 0}' "$WORK/trace")
echo
echo "loop thread in steady state: ${SLEEPS:-0} clock_nanosleep, ${FUTEX:-0} futex (doorbell; $FUTEX_NOT_WAKE not FUTEX_WAKE), $OTHER other, over $CYCLES cycles"
if [ "$OTHER" -eq 0 ] && [ "$FUTEX_NOT_WAKE" -eq 0 ] && [ "$CYCLES" -ge 10000 ]; then
  echo "VERDICT: PASS - the loop thread made only clock_nanosleep and futex-wake system calls in steady state"
else
  echo "VERDICT: FAIL - see the loop thread's rows above (or fewer than 10 000 cycles were traced)"
fi
