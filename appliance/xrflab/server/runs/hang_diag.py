"""Where a hung loop was: the safety watcher's look at its threads, in words.

When the safety watcher declares a hang (no cycle for ``hang_timeout_ms``) it reads, before the
kill, a few /proc files of each of the loop process's threads (rt_core/src/watch.c ``diagnose``:
stat, status, wchan, syscall, schedstat twice 10 ms apart, the kernel stack where readable; the
other programs' runnable real-time threads). This
module turns those records into a diagnosis an educator can read: for each thread its state, the
kernel function it waits in, its system call, its scheduling policy and priority, its CPU, its
context switches, and whether it was on a CPU, waiting for one or asleep in the millisecond
between the two looks; plus the run cgroup's throttling and memory counters (read after the kill:
they only count up) and the machine's real-time throttling setting. One sentence of it goes into
the run's end note, the whole into ``hang-diagnosis.json`` in the run's folder.

The difference that matters (docs/developers/safety.md, "Hang diagnosis"): a controller's
infinite loop is its loop thread in state R, on a CPU, in user code (no system call); a loop
blocked in the kernel is state S or D with a wait channel and a system call (a read on a pipe, a
futex, a sleep); a loop asleep in its own cycle's sleep (``clock_nanosleep``) long past its
deadline was never woken: the machine's timer, not the controller.

Every byte came from the guest's own /proc entries, whose names (``comm``) the guest sets: each
record is bounded by the C side, parsed here by length (never scanned for a separator), and the
text kept is cut short and stripped to printable ASCII.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import struct
from pathlib import Path
from typing import Any

from ...channels import lib
from ...runfolder import RunFolder
from . import cgroups

RECORD = "hang-diagnosis.json"  # in the run's folder, beside xrf-watch.json
_REC = struct.Struct("=HHi")  # struct xrf_watch_diag_rec
_NAME_MAX = 32
_STACK_FRAMES = 24
_FRAME = re.compile(rb"^\[<[0-9a-fA-F]+>\] ([A-Za-z0-9_.]{1,80})")
_STATUS_KEYS = (
    "State",
    "Cpus_allowed_list",
    "voluntary_ctxt_switches",
    "nonvoluntary_ctxt_switches",
    "VmLck",
    "VmRSS",
    "SigPnd",
    "ShdPnd",
)
_POLICIES = {0: "SCHED_OTHER", 1: "SCHED_FIFO", 2: "SCHED_RR", 3: "SCHED_BATCH", 5: "SCHED_IDLE", 6: "SCHED_DEADLINE"}
_STATES = {
    "R": "running or runnable",
    "S": "asleep (interruptible)",
    "D": "asleep, uninterruptible (I/O, a page, a lock in the kernel)",
    "T": "stopped (a signal)",
    "t": "stopped by a debugger",
    "Z": "exiting (zombie)",
    "X": "dead",
    "I": "idle",
}
# The system calls a loop may be found in, by number (the machine's ABI): the few worth naming.
_SYSCALLS = {
    "x86_64": {
        0: "read",
        1: "write",
        7: "poll",
        17: "pread64",
        18: "pwrite64",
        19: "readv",
        20: "writev",
        23: "select",
        34: "pause",
        35: "nanosleep",
        61: "wait4",
        202: "futex",
        230: "clock_nanosleep",
        232: "epoll_wait",
        270: "pselect6",
        271: "ppoll",
        281: "epoll_pwait",
    },
    "aarch64": {
        63: "read",
        64: "write",
        65: "readv",
        66: "writev",
        67: "pread64",
        68: "pwrite64",
        72: "pselect6",
        73: "ppoll",
        98: "futex",
        101: "nanosleep",
        115: "clock_nanosleep",
        22: "epoll_pwait",
        260: "wait4",
    },
}
_SLEEPS = ("clock_nanosleep", "nanosleep")


def _text(raw: bytes, limit: int = 200) -> str:
    """Printable ASCII only, at most `limit` characters: what a guest wrote, shown safely."""
    return "".join(ch if 32 <= ord(ch) < 127 else "?" for ch in raw[:limit].decode("latin-1"))


def records(raw: bytes) -> list[tuple[int, int, bytes]]:
    """(kind, tid, data) of each record; stops at the first that does not fit."""
    out = []
    off = 0
    while off + _REC.size <= len(raw):
        kind, length, tid = _REC.unpack_from(raw, off)
        off += _REC.size
        if off + length > len(raw):
            break
        out.append((kind, tid, raw[off : off + length]))
        off += length
    return out


def _stat(data: bytes) -> dict[str, Any]:
    """The fields of /proc/.../stat after the name (which may hold anything, ')' too)."""
    close = data.rfind(b")")
    name = _text(data[data.find(b"(") + 1 : close], _NAME_MAX) if close > 0 else ""
    fields = data[close + 1 :].split() if close > 0 else []

    def num(i: int) -> int:  # field i (1-based, as proc(5) numbers them) of the whole line
        with contextlib.suppress(IndexError, ValueError):
            return int(fields[i - 3])
        return -1

    state = _text(fields[0], 1) if fields else "?"
    return {
        "name": name,
        "state": state,
        "minor_faults": num(10),
        "major_faults": num(12),
        "utime_ticks": num(14),
        "stime_ticks": num(15),
        "cpu": num(39),
        "rt_priority": num(40),
        "policy": _POLICIES.get(num(41), str(num(41))),
    }


def _status(data: bytes) -> dict[str, str]:
    out: dict[str, str] = {}
    for line in data.splitlines()[:80]:
        key, _, value = line.partition(b":")
        k = key.decode("latin-1")
        if k in _STATUS_KEYS:
            out[k] = _text(value.strip(), 64)
    return out


def _schedstat(data: bytes) -> tuple[int, int, int] | None:
    parts = data.split()
    if len(parts) < 3:
        return None
    try:
        return int(parts[0]), int(parts[1]), int(parts[2])
    except ValueError:
        return None


def _syscall(data: bytes, machine: str) -> str:
    """running | user (not in a system call) | the call's name or number."""
    words = data.split()
    if not words:
        return ""
    if words[0] == b"running":
        return "running"
    try:
        nr = int(words[0])
    except ValueError:
        return _text(words[0], 16)
    if nr < 0:
        return "user"
    return _SYSCALLS.get(machine, {}).get(nr, f"#{nr}")


def _stack(data: bytes) -> list[str]:
    frames = []
    for line in data.splitlines()[:_STACK_FRAMES]:
        m = _FRAME.match(line)
        if m:
            frames.append(m.group(1).decode("ascii"))
    return frames


def parse(raw: bytes, pid: int, machine: str | None = None) -> dict[str, Any]:
    """The diagnosis from the watcher's records: threads (the loop's first) and a verdict."""
    machine = machine or os.uname().machine
    threads: dict[int, dict[str, Any]] = {}
    meta: list[int] = []
    cgroup_lines: list[str] = []
    others: dict[int, dict[str, Any]] = {}
    for kind, tid, data in records(raw):
        if kind == lib.XRF_DIAG_META:
            with contextlib.suppress(ValueError):
                meta = [int(x) for x in data.split()[:4]]
            continue
        if kind == lib.XRF_DIAG_CGROUP:
            cgroup_lines = [_text(line, 300) for line in data.splitlines()[:16]]
            continue
        if kind == lib.XRF_DIAG_OTHER:
            if tid > 0 and tid not in others and len(others) < lib.XRF_WATCH_DIAG_OTHERS:
                others[tid] = {"tid": tid, **_stat(data)}
            continue
        if kind in (lib.XRF_DIAG_OTHER_SCHEDSTAT, lib.XRF_DIAG_OTHER_SCHEDSTAT2):
            if tid in others:
                key = "schedstat" if kind == lib.XRF_DIAG_OTHER_SCHEDSTAT else "schedstat2"
                others[tid][key] = _schedstat(data)
            continue
        if tid <= 0 or (tid not in threads and len(threads) >= lib.XRF_WATCH_DIAG_TASKS):
            continue
        t = threads.setdefault(tid, {"tid": tid})
        if kind == lib.XRF_DIAG_STAT:
            t.update(_stat(data))
        elif kind == lib.XRF_DIAG_STATUS:
            t["status"] = _status(data)
        elif kind == lib.XRF_DIAG_WCHAN:
            w = _text(data.strip(), 64)
            t["wchan"] = "" if w == "0" else w
        elif kind == lib.XRF_DIAG_SYSCALL:
            t["syscall"] = _syscall(data, machine)
        elif kind == lib.XRF_DIAG_STACK:
            t["stack"] = _stack(data)
        elif kind in (lib.XRF_DIAG_SCHEDSTAT, lib.XRF_DIAG_SCHEDSTAT2):
            t["schedstat" if kind == lib.XRF_DIAG_SCHEDSTAT else "schedstat2"] = _schedstat(data)
    for t in [*threads.values(), *others.values()]:
        a, b = t.pop("schedstat", None), t.pop("schedstat2", None)
        if a and b:
            # In the 10 ms between the looks: on a CPU (the counter moves at each tick while
            # the task runs), or not (waiting for a CPU, or asleep: the state tells which).
            t["oncpu_us"] = round((b[0] - a[0]) / 1000, 1)
            t["waiting_us"] = round((b[1] - a[1]) / 1000, 1)
            t["cpu_total_ms"] = round(b[0] / 1e6, 1)
            t["runqueue_wait_total_ms"] = round(b[1] / 1e6, 1)
    ordered = sorted(threads.values(), key=lambda t: (not _is_loop_thread(t, pid), t["tid"]))
    out: dict[str, Any] = {
        "pid": pid,
        "threads": ordered,
        "others_runnable_rt": list(others.values()),
        "cgroup": cgroup_lines,
    }
    if len(meta) == 4:
        t0, t1, t2, hb = meta
        out["window_us"] = round((t1 - t0) / 1000, 1)
        out["read_us"] = round((t2 - t0) / 1000, 1)
        out["since_last_cycle_ms"] = round((t0 - hb) / 1e6, 1) if hb > 0 else None
    out["verdict"] = verdict(ordered, pid, list(others.values()))
    return out


def _is_loop_thread(t: dict[str, Any], pid: int) -> bool:
    return t.get("policy") in ("SCHED_FIFO", "SCHED_RR")


def loop_thread(threads: list[dict[str, Any]], pid: int) -> dict[str, Any] | None:
    """The loop's thread: the real-time one of highest priority, else the main thread."""
    rt = [t for t in threads if _is_loop_thread(t, pid)]
    if rt:
        return max(rt, key=lambda t: t.get("rt_priority", 0))
    return next((t for t in threads if t["tid"] == pid), threads[0] if threads else None)


def _holders(others: list[dict[str, Any]], cpu: Any) -> str:
    """Other programs' real-time threads that ran on the loop's CPU between the two looks (the
    ones holding it), else those runnable there, in words ("" none)."""
    here = [o for o in others if o.get("cpu") == cpu]
    ran = [o for o in here if o.get("oncpu_us")]
    words = ", ".join(
        f"{o.get('name', '?')} (tid {o['tid']}, {o.get('policy', '?')} {o.get('rt_priority', '?')}, "
        f"{o.get('oncpu_us', '?')} µs on CPU {o.get('cpu', '?')})"
        for o in (ran or here)[:4]
    )
    if not words:
        return ""
    return ("ran on its CPU meanwhile: " if ran else "runnable on its CPU: ") + words


def verdict(threads: list[dict[str, Any]], pid: int, others: list[dict[str, Any]] | None = None) -> str:
    """One sentence: where the loop thread was (and who else was runnable at a real-time priority)."""
    t = loop_thread(threads, pid)
    if t is None:
        return "no thread of the loop process could be read (it was exiting)"
    cpu = t.get("cpu", "?")
    name = f"the loop thread ({t.get('name', '?')}, tid {t['tid']}, {t.get('policy', '?')}"
    name += f" {t.get('rt_priority', 0)}, CPU {cpu})" if t.get("rt_priority", 0) > 0 else ")"
    state = t.get("state", "?")
    call = t.get("syscall", "")
    where = t.get("wchan") or (t.get("stack") or [""])[0]
    oncpu = t.get("oncpu_us")
    holders = _holders(others or [], cpu)
    held = f"; real-time threads of other programs {holders}" if holders else ""
    if state == "R":
        if oncpu == 0:
            # Runnable for 10 ms without a tick on a CPU: not computing, kept off it (the
            # run-queue wait is only counted once it runs again).
            return (
                f"{name} was runnable but kept off its CPU (0 µs on it in 10 ms): a thread of equal or "
                f"higher real-time priority held the CPU{held}"
            )
        if call in ("user", "running"):
            return (
                f"{name} was running in user code (state R, {oncpu} µs on its CPU of 10 ms, no system "
                f"call): a busy loop in the controller, not the kernel{held}"
            )
        if not call:  # /proc/TID/syscall needs ptrace access to the guest (a root appliance's)
            return (
                f"{name} was computing (state R, {oncpu} µs on its CPU of 10 ms; where not readable): a busy "
                f"loop, most likely in the controller{held}"
            )
        return f"{name} was running in the kernel (state R, system call {call}, {oncpu} µs on its CPU of 10 ms){held}"
    if state in ("S", "D"):
        label = _STATES.get(state, state)
        if call in _SLEEPS:
            return (
                f"{name} was {label} in {call} (waiting in {where or '?'}), its cycle's own sleep unless the "
                f"controller sleeps itself: the wake-up was not delivered in time (the timer, or its CPU){held}"
            )
        return f"{name} was {label} in the kernel: system call {call or '?'}, waiting in {where or '?'} (blocked, not computing){held}"
    if state in ("T", "t"):
        return f"{name} was stopped (state {state}): a SIGSTOP or a debugger, not a computation"
    return f"{name} was in state {state} ({_STATES.get(state, '?')}){held}"


def cgroup_counters(cgroup_lines: list[str]) -> dict[str, dict[str, int]]:
    """The loop's cpu and memory cgroups' counters, from its /proc/PID/cgroup lines (v1:
    "N:cpu,cpuacct:/path", v2: "0::/path"): cpu.stat (nr_throttled, throttled time) and the
    memory events (v2 memory.events; v1 memory.failcnt, under_oom). Paths confined to the
    cgroup mounts; at most a few small files."""
    mounts: dict[str, str] = {}
    with contextlib.suppress(OSError):
        for line in Path("/proc/self/mountinfo").read_text().splitlines():
            left, _, right = line.partition(" - ")
            f, rest = left.split(), right.split()
            if len(f) >= 5 and len(rest) >= 3:
                if rest[0] == "cgroup2":
                    mounts.setdefault("", f[4])
                elif rest[0] == "cgroup":
                    for opt in rest[2].split(","):
                        if opt in ("cpu", "memory"):
                            mounts.setdefault(opt, f[4])
    out: dict[str, dict[str, int]] = {}
    for line in cgroup_lines:
        parts = line.split(":", 2)
        if len(parts) != 3 or ".." in parts[2] or "?" in parts[2]:
            continue
        controllers = parts[1].split(",") if parts[1] else [""]
        for c in controllers:
            if c not in ("cpu", "memory", "") or c not in mounts:
                continue
            folder = Path(mounts[c]) / parts[2].lstrip("/")
            names = {
                "cpu": ("cpu.stat",),
                "memory": ("memory.failcnt", "memory.oom_control"),
                "": ("cpu.stat", "memory.events"),
            }[c]
            for name in names:
                values = cgroups.counters(folder / name)
                if values:
                    out[f"{c or 'v2'}:{parts[2]}/{name}"] = values
    return out


def rt_throttle() -> str:
    """The machine's real-time throttling (sched_rt_runtime_us of sched_rt_period_us)."""
    with contextlib.suppress(OSError):
        runtime = Path("/proc/sys/kernel/sched_rt_runtime_us").read_text().strip()
        period = Path("/proc/sys/kernel/sched_rt_period_us").read_text().strip()
        return f"{runtime} of {period} us"
    return ""


def summary(diag: dict[str, Any]) -> str:
    """The run's end note's part: the verdict and what the counters add."""
    text = f"hang diagnosis: {diag['verdict']}"
    throttled = [
        f"{k} nr_throttled {v['nr_throttled']}"
        for k, v in diag.get("counters", {}).items()
        if k.endswith("cpu.stat") and v.get("nr_throttled")
    ]
    if throttled:
        text += f"; the CPU bandwidth limit throttled it ({', '.join(throttled)})"
    return text + f" ({RECORD} in the run's folder)"


def write(run_dir: str | Path, diag: dict[str, Any]) -> None:
    with RunFolder(run_dir) as rf:
        rf.replace(RECORD, json.dumps(diag, indent=1).encode())
