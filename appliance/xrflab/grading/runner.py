"""Running one scenario on one build: the controller on its simulated plant, headless, then its
log graded (docs/educators/grading.md, "How a scenario runs").

The runner is the host side of one loop, as the supervisor is for the bench but without the
bench: no lease, no hub, no browsers. It makes the loop's segment (a sealed memfd, as the
supervisor does: the loop cannot resize it; nothing is left in /dev/shm), starts the controller
through a `Launcher` (the local one for `xrf grade`; the appliance hands in the run sandbox's),
sends the scenario's commands and setpoints by *loop time* (the loop's cycle count over its
frequency, so simulated time needs nothing else here), and stops it in order at the end.

Nothing waits without a bound: the segment must be ready within `Limits.start_s`, each command
answered within `command_s`, the loop must keep cycling (`stall_s`) and be in RUN by the
scenario's `run_by`, and the whole run ends within `duration * wall_factor + slack_s` of wall
time; otherwise the process group is killed and the result says why (status `hung`, `crashed`,
`never_ran`, `start_failed`), and the checks it did not get through get 0 points.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import os
import resource
import signal
import stat
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from . import checks as chk
from .results import GradeResult
from .scenario import Scenario

VIRTUAL_TIME_ENV = "XRF_VIRTUAL_TIME"  # the loop runs on simulated time (issue 32, rt_core side)
MAX_LOG_FILES = 64  # files looked at in a run's logs folder (the loop wrote them: bounded)
MAX_OUTPUT_TAIL = 20  # the controller's last printed lines kept in the result
MAX_OUTPUT_READ = 64 << 10  # bytes of its output read for them
_counter = itertools.count(1)


@dataclass(frozen=True)
class Limits:
    start_s: float = 10.0  # the process has its segment ready
    command_s: float = 2.0  # a command is answered
    stall_s: float = 3.0  # the loop's cycle count does not move (a hung loop)
    wall_factor: float = 3.0  # real time allowed per second of scenario
    slack_s: float = 10.0  # and on top of it
    stop_s: float = 3.0  # stop + quit until the process is killed


class LoopProcess(Protocol):
    pid: int

    def poll(self) -> int | None: ...

    def kill(self) -> None: ...

    def wait(self, timeout: float) -> int | None: ...


@dataclass
class Started:
    """A controller a launcher started: its process, its segment (a sealed memfd the runner reads
    and closes), and what to do once it has ended (the sandbox's file system and cgroup)."""

    proc: LoopProcess
    shm_fd: int
    shm_name: str
    release: Callable[[], None] = lambda: None
    run_dir: Path | None = None  # where its output and log are, when the launcher chose (a run folder)
    run_id: int | None = None  # its run record, when it has one (the appliance's)


class Launcher(Protocol):
    """Starts a controller: `exe` with `env` (the XRF_* options), working and log folder
    `run_dir`, its output into run_dir/output.txt. Raises OSError/RuntimeError/ValueError when it
    cannot; a refused start is a result (start_failed), not an error of the grader."""

    def __call__(self, exe: Path, env: dict[str, str], run_dir: Path) -> Started: ...


class _Local:
    def __init__(self, proc: subprocess.Popen[bytes]) -> None:
        self.proc = proc
        self.pid = proc.pid

    def poll(self) -> int | None:
        return self.proc.poll()

    def kill(self) -> None:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.proc.pid, signal.SIGKILL)

    def wait(self, timeout: float) -> int | None:
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            return None


def _local_limits() -> None:
    # The bounds a TA's laptop wants on a student's code too: memory, file size, no core dumps.
    resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))
    resource.setrlimit(resource.RLIMIT_FSIZE, (512 << 20, 512 << 20))
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))


def local_launcher(exe: Path, env: dict[str, str], run_dir: Path) -> Started:
    """`xrf grade` on a TA's laptop or a course's CI: the controller as a child of ours (as `xrf run`
    starts one), in its own session (killed as a group), with rlimits; not the appliance's sandbox
    (the appliance's launcher is grading/sandbox.py)."""
    from ..channels import segment

    name = f"xrf-grade-{os.getpid()}-{next(_counter)}"
    shm_fd = segment.create_sealed(name)
    try:
        out_fd = os.open(run_dir / "output.txt", os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, 0o640)
        try:
            proc = subprocess.Popen(
                [str(exe)],
                env={
                    "PATH": "/usr/local/bin:/usr/bin:/bin",
                    "LANG": "C.UTF-8",
                    "HOME": str(run_dir),
                    **env,
                    "XRF_SHM": name,
                    "XRF_SHM_FD": str(shm_fd),
                },
                cwd=run_dir,
                stdin=subprocess.DEVNULL,
                stdout=out_fd,
                stderr=subprocess.STDOUT,
                pass_fds=(shm_fd,),
                start_new_session=True,
                preexec_fn=_local_limits,  # noqa: PLW1509 (no threads of ours touch the child before exec)
            )
        finally:
            os.close(out_fd)
    except BaseException:
        os.close(shm_fd)
        raise
    return Started(_Local(proc), shm_fd, name)


def loop_env(scenario: Scenario, run_dir: Path, virtual_time: bool) -> dict[str, str]:
    """The XRF_* options of a graded loop (docs/developers/architecture.md lists them)."""
    env = {
        "XRF_SIM": scenario.robot,
        "XRF_TRANSPORT": "sim",
        "XRF_BACKEND": "posix",
        "XRF_LOG_DIR": str(run_dir),
        "XRF_QUIET": "1",
        # No real-time priority: graded runs share the machine (a queue of them, the bench's run);
        # a simulated plant needs no guarantees, and a spinning student's loop must not starve us.
        "XRF_PRIO": "0",
        # If the grader dies the loop stops by itself.
        "XRF_HOST_TIMEOUT_MS": "3000",
        "XRF_HOST_TIMEOUT_ACTION": "stop",
    }
    if scenario.faults:
        env["XRF_SIM_FAULTS"] = scenario.faults
    if virtual_time:
        # Held between the scenario's events (_drive raises the limit): commands and setpoints
        # land on the same cycles as in real time (docs/rt_core/runtime.md "Simulated time").
        env[VIRTUAL_TIME_ENV] = "hold"
    return env


def _next_stop(scenario: Scenario, commands: list, cycles: int, freq: float, acted: int | None = None) -> int:
    """Simulated time: the cycle count the loop may run to before the host acts again (the next
    command, the next setpoint change, the end); a ramp or table changes every cycle. `acted`:
    the count the host decided the due events on; when the loop has gone past it (it ran on to
    its hold between the host's two looks) and an event fell due in between, it stays where it
    is (`cycles`), so the next look acts on it (without, the event passed unacted and the loop ran
    on to the one after: a step due at cycle 200 landed at 2274)."""
    if acted is not None and acted < cycles:
        passed = [c.at for c in commands]
        for s in scenario.setpoints:
            end = s.end if s.kind == "ramp" else (s.points[-1][0] if s.kind == "table" else s.start)
            if end > s.start and s.start * freq <= cycles and acted < end * freq:
                return cycles  # a ramp or table changing in between
            passed.append(s.start)
        if any(acted < math.ceil(x * freq - 1e-9) <= cycles for x in passed):
            return cycles
    due = [c.at for c in commands] + [scenario.duration]
    for s in scenario.setpoints:
        end = s.end if s.kind == "ramp" else (s.points[-1][0] if s.kind == "table" else s.start)
        if s.start * freq <= cycles < end * freq:
            return cycles + 1
        due.append(s.start)
    later = [math.ceil(x * freq - 1e-9) for x in due if math.ceil(x * freq - 1e-9) > cycles]
    return min(later) if later else cycles + 1


def grade_executable(
    scenario: Scenario,
    exe: Path,
    run_dir: Path,
    launcher: Launcher = local_launcher,
    limits: Limits = Limits(),
    virtual_time: bool | None = None,
    build: str = "",
) -> GradeResult:
    """Run `exe` through `scenario` with its log and output in `run_dir` (made; kept), grade it.
    Never raises for what the controller does; `virtual_time` None: $XRF_VIRTUAL_TIME decides."""
    from ..channels import Channels, ChannelsError

    wall0 = time.monotonic()
    if virtual_time is None:
        virtual_time = os.environ.get(VIRTUAL_TIME_ENV, "") == "1"
    result = GradeResult(scenario.name, "error", build=build or str(exe), virtual_time=virtual_time)
    run_dir.mkdir(parents=True, exist_ok=True)
    started: Started | None = None
    ch: Channels | None = None
    data = chk.RunData(columns={})
    t_start_ns = 0  # the run's first deadline (status), the origin of the log's time
    try:
        try:
            started = launcher(exe, loop_env(scenario, run_dir, virtual_time), run_dir)
        except (OSError, ValueError, RuntimeError) as exc:
            result.status, result.reason = "start_failed", f"the controller could not be started: {exc}"
            return _finish(result, scenario, data, run_dir, wall0, t_start_ns)
        proc, shm_fd, shm_name = started.proc, started.shm_fd, started.shm_name
        run_dir = started.run_dir or run_dir
        result.run = started.run_id
        deadline = time.monotonic() + limits.start_s
        while ch is None:
            try:
                ch = Channels.open_fd(shm_fd, shm_name, wait_s=0.2)
            except ChannelsError as exc:
                code = proc.poll()
                if code is not None:
                    result.status, result.reason = (
                        "crashed",
                        f"the controller ended before it was ready ({_exit_words(code)})",
                    )
                    break
                if time.monotonic() > deadline:
                    result.status, result.reason = "start_failed", f"not ready within {limits.start_s:g} s: {exc}"
                    break
        if ch is not None:
            _drive(scenario, ch, proc, limits, result, data)
    finally:
        if started is not None:
            _stop(ch, started.proc, limits)
        if ch is not None:
            with contextlib.suppress(Exception):
                result.missed = int(ch.status().missed)
                t_start_ns = int(ch.status().t_start_ns)
            with contextlib.suppress(Exception):
                # what the loop says it ran on, not what was asked: a launcher that dropped the
                # variable shows here (the sandbox's environment is an allow-list, guest.py)
                result.virtual_time = result.virtual_time and ch.virtual_time
            ch.close()
        if started is not None:
            os.close(started.shm_fd)
            started.release()
    return _finish(result, scenario, data, run_dir, wall0, t_start_ns)


def _drive(
    scenario: Scenario, ch: object, proc: LoopProcess, limits: Limits, result: GradeResult, data: chk.RunData
) -> None:
    """Commands and setpoints by loop time until the scenario's end or a reason to stop."""
    from ..channels import Channels, ChannelsError

    assert isinstance(ch, Channels)
    freq = float(ch.info.get("cycle_freq") or 0) or 1000.0
    commands = list(scenario.commands)
    starts = [c.at for c in commands if c.cmd == "start"]
    run_by = scenario.run_by or min(scenario.duration, max(starts) + 2.0)
    wall_end = time.monotonic() + scenario.duration * limits.wall_factor + limits.slack_s
    written: dict[str, float] = {}
    last_cycles, last_move = -1, time.monotonic()
    seen = ch.doorbell
    state = ""
    hold_next = False  # simulated time: hold the loop one cycle after a command (below)
    try:
        while True:
            # The status as it is now: its loop time decides which events are due, and an older
            # copy would let an event pass (in simulated time the loop then runs on to the next
            # one). None while the loop writes it (simulated time: while it runs flat out between
            # two holds): the next doorbell, the process and the wall clock still watched.
            st = ch.fresh_status()
            if st is None:
                if proc.poll() is None and time.monotonic() <= wall_end:
                    seen = ch.wait_doorbell(seen, 20)
                    continue
                st = ch.status()  # the last copy, for the reason given below
            # Loop time is the grid's: periods since the first, those the loop missed included
            # (after an overrun it skips to the next boundary: docs/rt_core/runtime.md).
            t = (st.cycles + st.missed) / freq
            if st.state_name != state:
                state = st.state_name
                data.states.append((t, state))
                if state == "RUN" and result.reached_run_s is None:
                    result.reached_run_s = t
                if state == "ERROR":
                    data.alarms.append(f"the controller went to ERROR at t = {t:.3f} s")
            data.reached = t
            now = time.monotonic()
            code = proc.poll()
            if code is not None:
                result.status = "crashed"
                result.reason = f"the controller ended at t = {t:.3f} s ({_exit_words(code)})"
                data.alarms.append(result.reason)
                return
            if t >= scenario.duration:
                result.status = "completed"
                return
            if st.cycles != last_cycles:
                last_cycles, last_move = st.cycles, now
            elif now - last_move > limits.stall_s:
                result.status = "hung"
                result.reason = f"the loop stopped cycling at t = {t:.3f} s (no cycle for {limits.stall_s:g} s)"
                data.alarms.append(result.reason)
                return
            if now > wall_end:
                result.status = "hung"
                result.reason = f"out of time: {scenario.duration:g} s of loop time not done in {scenario.duration * limits.wall_factor + limits.slack_s:g} s"
                data.alarms.append(result.reason)
                return
            if t > run_by and result.reached_run_s is None:
                result.status = "never_ran"
                result.reason = f"the controller was not in RUN by t = {run_by:g} s (state {state or '?'})"
                return
            while commands and commands[0].at <= t:
                c = commands.pop(0)
                hold_next = True
                answer = ch.wait_command(ch.send_command(c.cmd), timeout=limits.command_s)
                if not answer.accepted:
                    data.alarms.append(
                        f"'{c.cmd}' at t = {t:.3f} s refused in {answer.state_name}: {answer.reason or 'no answer'}"
                    )
            want = scenario.setpoints_at(t)
            if want and want != written:
                ch.write_ros2xeno(want)
                written = want
            ch.host_heartbeat()
            if result.virtual_time:
                # run_until counts cycles run; the scenario's events are due in periods.
                now_st = ch.fresh_status()
                if now_st is not None:  # else the hold stays where it is: the next round sets it
                    periods = now_st.cycles + now_st.missed
                    acted = st.cycles + st.missed
                    stop = _next_stop(scenario, commands, periods, freq, acted)
                    if hold_next:
                        # A command takes effect in the loop's next cycle: held right after it,
                        # the loop shows its new state at that cycle's time. Let run to the next
                        # event at once, it was seen only when a copy of the status happened to
                        # complete while the loop ran flat out (RUN at 8.55 s for a start at 8.0).
                        stop, hold_next = min(stop, periods + 1), False
                    ch.run_until(stop - now_st.missed)
            # A wait on the loop's doorbell (each cycle rings it), bounded: the poll of this loop.
            seen = ch.wait_doorbell(seen, 20)
    except (ChannelsError, ValueError) as exc:
        result.status, result.reason = "crashed", f"its shared memory broke the rules: {exc}"
        data.alarms.append(result.reason)


def _stop(ch: object, proc: LoopProcess, limits: Limits) -> None:
    """Stop, quit, and if it does not end, kill its process group."""
    from ..channels import Channels, ChannelsError

    if proc.poll() is None and isinstance(ch, Channels):
        for cmd in ("stop", "quit"):
            with contextlib.suppress(ChannelsError, ValueError, TimeoutError):
                ch.wait_command(ch.send_command(cmd), timeout=limits.command_s / 2)
        if proc.wait(limits.stop_s) is not None:
            return
    proc.kill()
    proc.wait(limits.stop_s)


def _exit_words(code: int) -> str:
    if code < 0 or code > 128:
        num = -code if code < 0 else code - 128
        try:
            return f"killed by {signal.Signals(num).name}"
        except ValueError:
            return f"signal {num}"
    return f"exit code {code}"


def _finish(
    result: GradeResult, scenario: Scenario, data: chk.RunData, run_dir: Path, wall0: float, t_start_ns: int = 0
) -> GradeResult:
    result.output_tail = _tail(run_dir / "output.txt")
    result.loop_time_s = round(data.reached, 6)
    log_path = find_log(run_dir, scenario.log)
    if log_path is not None:
        result.log = str(log_path)
        try:
            data.columns = read_columns(log_path, t_start_ns)
        except (OSError, ValueError) as exc:
            data.alarms.append(f"the log could not be read: {exc}")
    data.columns.setdefault("t", np.empty(0))
    data.missed = result.missed
    data.complete = result.status == "completed"
    data.reason = result.reason
    result.alarms = list(data.alarms)
    if result.status == "completed" and log_path is None:
        result.reason = "the controller wrote no log (its logger's variables are what the checks read)"
    result.checks = chk.evaluate(scenario, data)
    result.total()
    result.wall_s = round(time.monotonic() - wall0, 3)
    return result


def _tail(path: Path) -> list[str]:
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError:
        return []
    with os.fdopen(fd, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        f.seek(max(0, size - MAX_OUTPUT_READ))
        text = f.read(MAX_OUTPUT_READ).decode("utf-8", "replace")
    return [line[:300] for line in text.splitlines()[-MAX_OUTPUT_TAIL:]]


def find_log(run_dir: Path, stem: str = "") -> Path | None:
    """The run's log file: the newest regular file under run_dir/logs (bounded, no links followed)
    whose name starts with `stem` when given; per-cycle timing files are not it."""
    found: list[tuple[float, Path]] = []
    for folder in (run_dir / "logs", run_dir):
        try:
            entries = list(itertools.islice(os.scandir(folder), MAX_LOG_FILES))
        except OSError:
            continue
        for e in entries:
            if not e.is_file(follow_symlinks=False) or e.name in ("output.txt",) or e.name.startswith("cycle_timing"):
                continue
            if stem and not e.name.startswith(stem):
                continue
            if not e.name.endswith((".bin", ".xrf", ".xrflog")):
                continue
            st = e.stat(follow_symlinks=False)
            if stat.S_ISREG(st.st_mode):
                found.append((st.st_mtime, Path(e.path)))
        if found:
            break
    return max(found)[1] if found else None


def read_columns(path: Path, t_start_ns: int = 0) -> dict[str, np.ndarray]:
    """The log's variables as float arrays and `t` (s of loop time). With the run's first deadline
    (`t_start_ns`, the status's) `t` is each record's period on the grid: the whole periods from
    it to the cycle's start, so periods the loop missed leave gaps, as they did in the run (the
    start lies less than a period after its deadline unless the wake-up itself was that late).
    Without it: cycle / cycle_freq."""
    from ..logs.reader import open_log

    fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    try:
        log = open_log(path, fd=fd)
    finally:
        os.close(fd)
    if not log.segments:
        return {"t": np.empty(0)}
    log.check_uniform()
    rec = log.records
    freq = float(log.segments[0].header.get("cycle_freq") or 0) or 1000.0
    cols: dict[str, np.ndarray] = {}
    names = rec.dtype.names or ()
    if t_start_ns > 0 and "t_ns" in names:
        periods = ((rec["t_ns"].astype(np.int64) - t_start_ns) * int(freq)) // 1_000_000_000
        cols["t"] = np.maximum(periods, 0).astype(np.float64) / freq
    elif "cycle" in names:
        cols["t"] = rec["cycle"].astype(np.float64) / freq
    else:
        cols["t"] = np.arange(len(rec)) / freq
    for v in log.variables:
        if rec[v.field].ndim == 1:
            cols[v.field] = rec[v.field].astype(np.float64)
    return cols


def grade_project(
    scenario: Scenario,
    project_dir: Path,
    work_dir: Path,
    launcher: Launcher = local_launcher,
    limits: Limits = Limits(),
    virtual_time: bool | None = None,
    log: Callable[[str], None] = lambda _line: None,
) -> GradeResult:
    """Build `project_dir` (in work_dir/build) and grade it; a failed build is a result too."""
    from .. import build

    wall0 = time.monotonic()
    try:
        built = build.build_project(project_dir, work_dir / "build", log=log)
    except Exception as exc:  # any build failure is the student's result, not ours to raise
        result = GradeResult(
            scenario.name, "build_failed", reason=f"the build failed: {str(exc)[:2000]}", build=str(project_dir)
        )
        result.checks = chk.evaluate(
            scenario, chk.RunData(columns={"t": np.empty(0)}, complete=False, reason="the build failed")
        )
        result.total()
        result.wall_s = round(time.monotonic() - wall0, 3)
        return result
    return grade_executable(
        scenario, Path(built.executable), work_dir / "run", launcher, limits, virtual_time, build=str(project_dir)
    )
