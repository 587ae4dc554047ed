"""Watching a live run from outside: its safety watcher, the heartbeats, its disk use, its exit.

Safety: every run with open shared memory has a safety watcher (server/runs/safety.py, rt_core's
watch.c): a C thread outside the event loop, woken by the kernel when the loop process exits, that
checks the loop's heartbeat every few milliseconds. On an exit, or a hang (no cycle for
``hang_timeout_ms``: it kills the loop), it puts the outputs in a safe state first (the simulated
board's ``forced_off``, or an FPGA RESET over spidev on a real bench) and only then tells us
through an eventfd (`on_watch`). A busy event loop delays the record, never the safe outputs.

The heartbeat task writes the host heartbeat the loop checks (XRF_HOST_TIMEOUT_MS: the loop
pauses itself if the appliance dies or hangs) and, only where no watcher could start, detects a
hang itself. The limits guard stops a run that went over what the kernel bounds (server/runs/limits.py:
memory, processes, its run folder's file system), from the run's start. `wait_for_exit`
is the run's last word: the launcher's exit, the watcher's account of it, and safe outputs where
no watcher made them so; server/runs/end.py then records how the run ended.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import functools
import logging
import os
import signal
import subprocess
import time
from pathlib import Path

from ... import build, plants
from ...channels import ChannelsError, ffi, lib
from ...profiles import ProfileError, SafeReaction, bench_profile_name, load_profile, safe_reaction
from ...runfolder import RunFolder
from ...ticks import until_aligned
from ..settings import Settings
from ..ws.hub import Hub
from ..ws.messages import AlarmMessage
from . import watch_record
from .control import terminate
from .limits import RunLimits
from .run import Run
from .safety import SPI_SPEED_HZ, SafetyWatcher, WatchResult, fpga_reset, hold_message
from .store import RunStore

log = logging.getLogger("xrflab.supervisor")


# ---- the safety watcher -------------------------------------------------------------------------


def start_watcher(run: Run, settings: Settings) -> None:
    """The safety watcher for a run whose shared memory is open (server/runs/safety.py)."""
    ch = run.channels
    assert ch is not None
    info = ch.info
    # A slow loop (10 Hz) beats less often than the default timeout: a hang is three
    # missed periods at the least, never one long cycle.
    period_ms = 1000 // max(1, int(info.get("cycle_freq", 0)) or 1)
    hang_ms = max(settings.hang_timeout_ms, 3 * period_ms)
    # Above any real-time priority the run may take (the launcher caps it below this one), and
    # off the run's CPUs where its cpuset holds: the run's own threads cannot starve the watcher.
    prio = settings.watch_priority
    lim = run.limits
    avoid = lim.cpus if lim is not None and not lim.layers.get("cpu") else set()
    real = settings.bench_is_real()
    reaction = run_safe_reaction(run.row.sim, real, settings)
    if real and reaction.name == "hold" and os.environ.get("XRF_TRANSPORT") == "evl-spidev":
        # bench_refusal refuses such a run at start; should one get here all the same: the
        # watcher follows the arm's counters with in-band transfers while the loop runs, a loop
        # on EVL's out-of-band SPI holds the bus, and a watcher blocked in a transfer could not
        # act at all. Zero (the FPGA RESET) is what it can always do.
        log.warning("run %s: hold needs the in-band spidev transport (XRF_TRANSPORT=evl-spidev): zero", run.row.id)
        reaction = safe_reaction(None)
    try:
        w = SafetyWatcher(
            run.row.pid or run.proc.pid,
            ch,
            hang_timeout_ms=hang_ms,
            check_ms=max(2, min(20, hang_ms // 10)),
            force_sim=info.get("transport", "sim") == "sim",
            spi_device=settings.spi_bench() if real else "",
            rt_priority=max(0, prio),
            avoid_cpus=avoid,
            safe_reaction=reaction.name,
            brake_channel=reaction.brake_channel,
            host_beat_ms=int(settings.host_heartbeat_period_s * 1000),
            host_grace_ms=settings.host_stall_grace_ms,
            **hold_config(reaction, run.row.sim or settings.sim, real),
        )
    except (OSError, ValueError) as exc:  # ESRCH: the loop is already gone; wait_for_exit handles it
        log.warning("run %s: no safety watcher (%s); the event loop watches instead", run.row.id, exc)
        return
    run.watcher = w
    if real and reaction.name == "hold":
        status, channel = w.hold_ready()
        if status:  # said now, not first found out at a fault
            log.warning("run %s: %s", run.row.id, hold_message(status, channel))
    asyncio.get_running_loop().add_reader(w.fileno(), on_watch, run)
    if reaction.name == "hold":
        start_backup(run, reaction, settings)


@functools.cache
def _watch_exe() -> Path:
    """rt_core's xrf-watch, from the install every run's build links (built once per content)."""
    return Path(build.ensure_rt_core(log=lambda line: None)) / "bin" / "xrf-watch"


def start_backup(run: Run, reaction: SafeReaction, settings: Settings) -> None:
    """xrf-watch beside the thread (docs/developers/safety.md "When the appliance dies"): if this
    process dies first, it kills the loop and holds and lowers the arm. In a session of its own
    (not tied to us), handed our descriptor of the segment; it leaves by itself when the loop
    ends first, and wait_for_exit reaps it."""
    if run.shm_fd < 0:
        log.warning("run %s: no segment descriptor: no backup watcher for the arm", run.row.id)
        return
    # The run folder as RunFolder opens it (no link followed), handed over: where xrf-watch writes
    # what it did if we are gone (server/runs/watch_record.py reads it back after a restart).
    folder: RunFolder | None = None
    try:
        exe = _watch_exe()
        folder = RunFolder(run.run_dir)
        run.backup = subprocess.Popen(
            [str(exe), "--shm-fd", str(run.shm_fd), "--loop", str(run.row.pid or run.proc.pid)]
            + ["--host", str(os.getpid()), "--reaction", reaction.name]
            + (
                ["--spi", ",".join(settings.spi_bench()), "--plant", reaction.robot, "--counts-per-rev"]
                + [str(reaction.counts_per_rev), "--enc-inverted", str(reaction.enc_inverted)]
                + ["--pwm-reversed", str(reaction.pwm_reversed)]
                if settings.bench_is_real()
                else ["--plant", run.row.sim or settings.sim]
            )
            + ["--rt-priority", str(max(0, settings.watch_priority))]
            + ["--record-dir-fd", str(folder.fd), "--record", watch_record.RECORD],
            pass_fds=(run.shm_fd, folder.fd),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            start_new_session=True,
        )
    except (OSError, build.BuildError) as exc:
        log.warning("run %s: no backup watcher for the arm (%s)", run.row.id, exc)
    finally:
        if folder is not None:
            folder.close()


def hold_config(reaction: SafeReaction, plant: str, real: bool) -> dict[str, int]:
    """The watcher's `hold` settings: the arm's plant row (the run's simulated plant; on a real
    bench the bench profile's robot) and, on a real bench, the profile's encoder scale and wiring
    (docs/developers/safety.md, "hold on a real bench"). Empty for the other reactions."""
    if reaction.name != "hold":
        return {}
    if not real:
        return {"plant": hold_plant(plant)}
    return {
        "plant": hold_plant(reaction.robot),
        "enc_counts_per_rev": reaction.counts_per_rev,
        "enc_inverted": reaction.enc_inverted,
        "pwm_reversed": reaction.pwm_reversed,
    }


def bench_refusal(settings: Settings) -> str:
    """Why a run may not start on this real bench, or "": every ico board its profile's channels
    need (channels.h: 4 per board) must have its SPI device configured (Settings.spi_devices, one
    per board) and open as one, or the loop could not reach it and the safety watcher's frames
    could not make it safe."""
    if not settings.bench_is_real():
        return ""
    name = bench_profile_name("", True)
    if not name:
        return ""
    try:
        profile = load_profile(name, settings.data_dir)
    except ProfileError:
        return ""  # run_safe_reaction says so; the bench is then one board, as without a profile
    channels = max((int(ch["channel"]) for ch in profile.get("channels") or []), default=1)
    per_board = int(lib.XRF_ICO_CHANNELS)
    boards = -(-channels // per_board)
    if os.environ.get("XRF_TRANSPORT") == "evl-spidev":
        # The out-of-band transport gives the loop the bus: the watcher's in-band count samples
        # (hold's) would block behind it, and it reaches one board (evl_spidev.c).
        if safe_reaction(profile).name == "hold":
            return (
                f"bench profile {name!r} needs the safe reaction 'hold' (an arm that falls when its motors are off): "
                "the safety watcher follows the arm over in-band SPI beside the loop, and XRF_TRANSPORT=evl-spidev "
                "gives the bus to the loop, so on a fault the watcher could only drop the arm. Use XRF_TRANSPORT=spidev "
                "(or auto) on this bench (docs/developers/safety.md)"
            )
        if boards > 1:
            return (
                f"bench profile {name!r} has {channels} channels on {boards} ico boards, and XRF_TRANSPORT=evl-spidev "
                "drives one board: use XRF_TRANSPORT=spidev (or auto) with one device per board in XRF_SPI_DEVICES "
                "(docs/install/pi.md)"
            )
    devices = settings.spi_bench()
    if len(devices) < boards:
        return (
            f"bench profile {name!r} has {channels} channels on {boards} ico boards, but "
            f"{len(devices)} SPI device{'s' if len(devices) > 1 else ''} {'are' if len(devices) > 1 else 'is'} "
            f"configured ({', '.join(devices)}): board {len(devices) + 1}'s device is missing. Set XRF_SPI_DEVICES "
            f"to one device per board, board 1 first (e.g. {','.join(SPI_EXAMPLE)}; docs/install/pi.md)"
        )
    return spi_problem(devices[:boards])


# The Pi's chip selects for boards 2 and 3 after board 1's default (docs/install/pi.md).
SPI_EXAMPLE = (Settings.spi_device, "/dev/spidev0.1", "/dev/spidev1.0")


def spi_problem(devices: tuple[str, ...]) -> str:
    """Nothing ("") when every board's device opens as an SPI device (rt_core's own open: xrf_spi_probe),
    else which one does not and why."""
    failed = ffi.new("int32_t *")
    r = lib.xrf_spi_probe(",".join(devices).encode(), SPI_SPEED_HZ, failed)
    if r == 0:
        return ""
    which = (
        f"board {failed[0] + 1}'s SPI device {devices[failed[0]]}" if 0 <= failed[0] < len(devices) else "SPI devices"
    )
    why = {
        -errno.ENOENT: "does not exist",
        -errno.ENOTTY: "is not an SPI device (a regular file or another kind of device)",
        -errno.EISDIR: "is a folder, not an SPI device",
        -errno.EACCES: "is not read/writable by the appliance",
    }.get(r, f"cannot be opened: {os.strerror(-r)}")
    return f"{which} {why} (errno {-r})"


def hold_plant(name: str) -> int:
    """The plant table's id of the simulated arm `hold` steps on (0: none, which the watcher
    refuses: the run is then watched by the event loop, said in the log)."""
    try:
        return plants.get(name).id
    except KeyError:
        return 0


def run_safe_reaction(plant: str, real: bool, settings: Settings) -> SafeReaction:
    """The bench profile's safe reaction (profiles.safe_reaction): the plant's profile on a
    simulated board (the run's plant as the appliance chose it, never the segment's own
    xrf_info.sim: the loop writes that), XRF_BENCH_PROFILE's on a real one. A bench with no
    usable profile gets `zero`, today's reaction, said in the log."""
    name = bench_profile_name(plant or settings.sim, real)
    if not name:
        return safe_reaction(None)
    try:
        return safe_reaction(load_profile(name, settings.data_dir))
    except ProfileError as exc:
        log.warning("bench profile %r unusable (%s): the safety watcher zeroes the outputs", name, exc)
        return safe_reaction(None)


def on_watch(run: Run) -> None:
    """The watcher acted (outputs already safe): take note. The record follows the exit."""
    w = run.watcher
    if w is None:
        return
    with contextlib.suppress(ValueError, OSError):
        asyncio.get_running_loop().remove_reader(w.fileno())
    result = w.result()
    if result is not None:
        take_watch(run, result)


def take_watch(run: Run, result: WatchResult) -> None:
    if not result.acted or run.watch is not None:
        return
    run.watch = result
    run.safe_state = result.describe()
    run.exited_at = result.event_ns / 1e9
    run.safe_at = result.safe_ns / 1e9
    if result.reason == "hang":
        run.hang = True
        if result.kill_status != 0:  # could not kill it through the pidfd: the launcher can
            with contextlib.suppress(ProcessLookupError):
                run.proc.send_signal(signal.SIGKILL)


def safe_state(run: Run, settings: Settings) -> None:
    """Outputs off where no watcher did it (the loop died before its memory was open, or the
    watcher could not start)."""
    if run.safe_state:
        return
    transport = run.channels.info.get("transport", "sim") if run.channels else ""
    if run.channels is not None and transport == "sim":
        run.channels.force_sim_outputs_off()
        run.safe_state = "sim outputs forced off"
    elif settings.bench_is_real():
        run.safe_state = fpga_reset(",".join(settings.spi_bench()))
    else:
        # The simulated board lives inside the loop process: with no shm it died with it.
        run.safe_state = "simulated board ended with the process"
    run.safe_at = time.monotonic()


async def wait_for_exit(run: Run, settings: Settings) -> int:
    """Wait for the loop process to end; its return code, once the outputs are safe."""
    returncode = await run.proc.wait()
    if run.watcher is not None:
        w = run.watcher
        with contextlib.suppress(ValueError, OSError):
            asyncio.get_running_loop().remove_reader(w.fileno())
        # The exit has happened: stop() lets the thread handle it first if it has not yet.
        final = await asyncio.to_thread(w.stop)  # for `hold`: once the arm is at rest
        take_watch(run, final)
        run.watch_final = final
    if run.backup is not None:  # it saw the loop end first and leaves by itself
        try:
            await asyncio.to_thread(run.backup.wait, 10)
        except subprocess.TimeoutExpired:
            run.backup.kill()
            await asyncio.to_thread(run.backup.wait)
    if not run.exited_at:
        run.exited_at = time.monotonic()
    safe_state(run, settings)
    return returncode


# ---- heartbeats ---------------------------------------------------------------------------------

ALIVE_PERIOD_S = 1.0  # "the event loop is alive" to the safety watcher, on the whole second


async def heartbeat(run: Run, settings: Settings) -> None:
    """Host heartbeat out, loop heartbeat in (hang detection where no watcher runs).

    Where the safety watcher runs (the usual case) it detects a hang itself, every few ms in C,
    and its thread writes the host heartbeat host_heartbeat_period_s apart for
    host_stall_grace_ms after this task last said the event loop is alive (watch.h,
    host_beat_ns): the beat the loop's host timeout counts on is the watcher's, which dies with
    this process (the loop pauses within host_timeout_ms of the appliance's death, as before).
    So this task only says "alive" (and beats too, for good measure) once a second, on the
    whole second with the appliance's other once-a-second work (`until_aligned`), not 5 times
    a second on a timer of its own (issue 30 item 4: a fifth of the idle appliance's Python
    time): an event loop that stops running still pauses the run, after the grace less at most
    ALIVE_PERIOD_S (4-5 s instead of 4.8-5 s). Without a watcher this task is the only beat:
    host_heartbeat_period_s apart (at most a quarter of host_timeout_ms, so the loop pauses only
    after three missed beats), and it also reads the loop's heartbeat, a quarter of
    hang_timeout_ms apart."""
    ch = run.channels
    assert ch is not None
    hang_ns = settings.hang_timeout_ms * 1_000_000
    beat_s = min(settings.host_heartbeat_period_s, settings.host_timeout_ms / 4000)
    # A sign of life at least four times per grace: a short grace (tests) keeps its meaning.
    alive_s = min(ALIVE_PERIOD_S, settings.host_stall_grace_ms / 4000)
    last_good = time.monotonic_ns()
    while run.alive:
        ch.host_heartbeat()
        if run.watcher is not None:
            run.watcher.host_alive()  # it beats on our behalf while we were alive within the grace
            await asyncio.sleep(until_aligned(alive_s))
            continue
        now = time.monotonic_ns()
        try:
            s = ch.status()
        except ChannelsError:
            s = None  # seqlock held: a loop stopped mid-write looks exactly like this
        if s is not None:
            run.last_status = s
            stale = s.running and s.heartbeat_ns > 0 and now - s.heartbeat_ns > hang_ns
            if not stale:
                last_good = now
        if now - last_good > hang_ns and run.alive:
            run.hang = True
            safe_state(run, settings)
            run.exited_at = time.monotonic()
            with contextlib.suppress(ProcessLookupError):
                run.proc.send_signal(signal.SIGKILL)
            return
        await asyncio.sleep(min(beat_s, settings.hang_timeout_ms / 4000))


# ---- the kernel's limits -------------------------------------------------------------------------

# A guard, not a bound: the kernel has refused the page, the fork or the write already; the guard
# only ends the run and says why (and a run that ends first is named by the same look at its
# end: end.record). Every 4 s, on the 4-second boundaries the idle reader wakes on (it was four
# times a second, then once: issue 30 item 4; its cgroup files and statvfs were a tenth of the
# idle event loop's Python, session 14): a run over a limit is stopped up to 4 s after the kernel
# refused it, not 1 s.
LIMITS_PERIOD_S = 4.0
WATCHED_DISK_EVERY = 1  # looks (4 s): walking a run folder is not free (every 2 s before)
LIMIT_REASONS = ("memory", "pids", "disk", "cpu")


def announce_limit(run: Run, over: tuple[str, str], store: RunStore, hub: Hub) -> None:
    """The run went over a limit: it ends with that name, its record says why, everyone is told."""
    reason, message = over
    run.end_reason = run.end_reason or reason
    run.row = store.update(run.row.id, message=message)
    publish_limit_alarm(run, reason, message, hub)


def publish_limit_alarm(run: Run, reason: str, message: str, hub: Hub) -> None:
    """The alarm of a limit (kind = runs.END_REASONS' name), once per run."""
    if run.limit_alarm:
        return
    run.limit_alarm = reason
    hub.publish(AlarmMessage(kind=reason, run_id=run.row.id, end_reason=reason, message=message))


async def limits_guard(run: Run, limits: RunLimits, settings: Settings, store: RunStore, hub: Hub) -> None:
    """From the run's start (before its shared memory exists): the kernel already refuses what
    goes over a limit (a page, a fork, a write); once the run did, it is stopped with an alarm of
    that kind. A few cgroup counters and one statvfs, every LIMITS_PERIOD_S: read here, not in a
    worker thread (the default executor's few threads may all be waiting on something slow)."""
    looks = 0
    while run.alive and not run.ended.is_set():
        await asyncio.sleep(until_aligned(LIMITS_PERIOD_S))  # with the reader's idle batch
        looks += 1
        try:
            over = limits.over()
            if over is None and limits.walks_disk and looks % WATCHED_DISK_EVERY == 0:  # no file system of its own
                over = await asyncio.to_thread(limits.watched_disk_over)
        except Exception:  # never let the guard die quietly: the run would go on unwatched
            log.exception("run %s: reading its limits failed", run.row.id)
            continue
        if over is not None and run.alive and not run.ended.is_set():
            log.warning("run %s: %s", run.row.id, over[1])
            announce_limit(run, over, store, hub)
            run.stop_requested = True
            await terminate(run, settings)
            return
