"""The supervisor: builds, starts, watches and stops loop processes, one run at a time.

A run is one loop process plus its shared memory (/dev/shm/<name>, a fresh name per run). The
supervisor owns that memory: it opens it with ``Channels``, writes the host heartbeat the loop
checks (XRF_HOST_TIMEOUT_MS: the loop pauses itself if we die), reads state/telemetry/monitor
when the loop rings the doorbell, and unlinks the object when the run is over.

Safety: every run with open shared memory has a safety watcher (server/safety.py, rt_core's
watch.c): a C thread outside the event loop, woken by the kernel when the loop process exits, that
checks the loop's heartbeat every few milliseconds. On an exit, or a hang (no cycle for
``hang_timeout_ms``: it kills the loop), it puts the outputs in a safe state first (the simulated
board's ``forced_off``, or an FPGA RESET over spidev on a real bench) and only then tells us
through an eventfd. This module then records the run's end, names how it ended (``end_reason``)
and raises the alarm. A busy event loop delays the record, never the safe outputs.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import shutil
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .. import channels as chmod
from .. import guest, plants
from ..channels import Channels, ChannelsError
from ..logs import live as loglive
from .children import Child
from .guest_spawn import GuestReport, GuestSpawner
from .hub import Hub
from .lifecycle import RunLifecycle
from .runs import END_REASONS, RunRow, RunStore
from .safety import SafetyWatcher, WatchResult, fpga_reset
from .settings import Settings

STATE_RUN = chmod.lib.XRF_STATE_RUN
STATE_PAUSED = chmod.lib.XRF_STATE_PAUSED
STATE_STOPPED = chmod.lib.XRF_STATE_STOPPED
STATE_ERROR = chmod.lib.XRF_STATE_ERROR
SETTLING = {
    chmod.lib.XRF_STATE_INITIALISING,
    chmod.lib.XRF_STATE_STOPPING,
    chmod.lib.XRF_STATE_PAUSING,
}
SOURCE_APPLIANCE = chmod.lib.XRF_SOURCE_APPLIANCE
log = logging.getLogger("xrflab.supervisor")
DOORBELL_WAIT_MS = 50  # also the fallback poll period if a loop never rings


class SupervisorError(Exception):
    """A request the supervisor cannot honour; `status` is the HTTP status to answer with."""

    def __init__(self, message: str, status: int = 409) -> None:
        super().__init__(message)
        self.status = status


def _folder_bytes(path: Path) -> int:
    total = 0
    for dirpath, _dirs, files in os.walk(path):
        for f in files:
            with contextlib.suppress(OSError):
                total += os.lstat(os.path.join(dirpath, f)).st_blocks * 512
    return total


def _parent_of(pid: int) -> int:
    """The parent pid from /proc/<pid>/stat (world-readable, whoever owns the process); 0 if gone."""
    try:
        return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return 0


def _alive(pid: int) -> bool:
    """The process exists and is not a zombie."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def _last_logged_seq(ch: Channels, run_dir: Path) -> int | None:
    """The `seq` of the last record in the run's log file (the one the loop's log_meta names),
    None if there is none yet."""
    from ..logs.reader import open_log
    from ..logs.runfolder import RunPathError, confine

    meta = ch.shm.log_meta
    published = chmod.ffi.string(meta.path, chmod.lib.XRF_PATH_MAX).decode("utf-8", "replace")
    try:
        path = run_dir / confine(run_dir, published)
        records = open_log(path).records
    except (RunPathError, OSError, ValueError, KeyError):  # no file yet, or nothing readable in it
        return None
    return int(records["seq"][-1]) if len(records) else None


def remove_shm(name: str) -> None:
    """Unlink a run's shared memory and the run's folder of it in /dev/shm (xrflab.guest)."""
    try:
        path = chmod.shm_path(name)
    except ValueError:
        return
    if path.parent != chmod.SHM_DIR:
        shutil.rmtree(path.parent, ignore_errors=True)
        return
    with contextlib.suppress(FileNotFoundError):
        path.unlink()
    if name.endswith(guest.UNCONFINED_SUFFIX):  # its (unused) shm folder lies beside it
        shutil.rmtree(chmod.SHM_DIR / name.removesuffix(guest.UNCONFINED_SUFFIX), ignore_errors=True)


# ---- bundled builds -----------------------------------------------------------------------------


@dataclass
class BuildEntry:
    name: str
    kind: str  # example | template
    path: Path
    sim: str
    status: str = "not built"  # not built | building | ready | failed
    executable: Path | None = None
    error: str = ""
    log_tail: list[str] = field(default_factory=list)
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)


class BuildCatalog:
    """The projects that come with the appliance, built on first use in a worker thread."""

    def __init__(self, settings: Settings, publish: Callable[[str, dict[str, Any]], None]) -> None:
        self._settings = settings
        self._publish = publish
        self._entries: dict[str, BuildEntry] = {}
        # Builds made elsewhere (uploaded projects, xrflab.projects): runnable by name, not listed.
        self._external: dict[str, BuildEntry] = {}
        self.scan()

    def scan(self) -> None:
        for kind, folder in (("example", "examples"), ("template", "templates")):
            root = self._settings.projects_dir / folder
            if not root.is_dir():
                continue
            for project in sorted(p for p in root.iterdir() if (p / "CMakeLists.txt").is_file()):
                name = project.name if kind == "example" else f"template-{project.name}"
                if name not in self._entries:
                    sim = project.name if project.name in plants.names() else self._settings.sim
                    self._entries[name] = BuildEntry(name, kind, project, sim)

    def entries(self) -> list[BuildEntry]:
        self.scan()  # examples may appear while we run (a fresh checkout being filled in)
        return list(self._entries.values())

    def add_external(self, name: str, path: Path, executable: Path, sim: str) -> BuildEntry:
        """Register a finished build of an uploaded project so start_run() can start it by name."""
        entry = BuildEntry(name, "project", path, sim, status="ready", executable=executable)
        self._external[name] = entry
        return entry

    def get(self, name: str) -> BuildEntry:
        if name in self._external:
            return self._external[name]
        self.scan()
        if name not in self._entries:
            raise SupervisorError(f"no build named {name!r}; have: {', '.join(self._entries)}", 404)
        return self._entries[name]

    async def ensure_built(self, name: str) -> BuildEntry:
        entry = self.get(name)
        async with entry.lock:  # one build per project at a time; later callers reuse it
            if entry.status == "ready" and entry.executable and entry.executable.exists():
                return entry
            entry.status, entry.error, entry.log_tail = "building", "", []
            loop = asyncio.get_running_loop()

            def log(line: str) -> None:  # called from the build thread
                entry.log_tail = (entry.log_tail + [line])[-200:]
                loop.call_soon_threadsafe(self._publish, "build", {"build": name, "line": line})

            def work() -> Path:
                from .. import build

                # One build folder per rt_core install: a CMake cache remembers the XrfRt it
                # found first, so reusing a folder across rt_core versions would link the old one.
                prefix = build.ensure_rt_core(log)
                build_dir = self._settings.builds_dir / name / Path(prefix).name
                result = build.build_project(entry.path, build_dir, log=log)
                return Path(result.executable)

            self._publish("build", {"build": name, "status": "building"})
            try:
                entry.executable = await asyncio.to_thread(work)
            except Exception as exc:  # BuildError and anything unexpected: the user sees why
                entry.status, entry.error = "failed", str(exc).splitlines()[0] if str(exc) else repr(exc)
                self._publish("build", {"build": name, "status": "failed", "error": entry.error})
                raise SupervisorError(f"build {name} failed: {entry.error}", 422) from exc
            entry.status = "ready"
            self._publish("build", {"build": name, "status": "ready"})
            return entry


# ---- one run ------------------------------------------------------------------------------------


def schema_fields(schema: str) -> list[dict[str, Any]]:
    """[{name, type}] from a normalised .msg text, for the dashboard's controls and plots."""
    from ..msgdef import Codec

    return [{"name": f.name, "type": f.type, "count": f.count} for f in Codec(schema).fields]


@dataclass
class Run:
    row: RunRow
    proc: Child  # the run sandbox's launcher (its exit mirrors the controller's)
    shm: str
    run_dir: Path
    build: BuildEntry
    channels: Channels | None = None
    stop_requested: bool = False
    hang: bool = False
    safe_state: str = ""
    exited_at: float = 0.0
    safe_at: float = 0.0
    ended: asyncio.Event = field(default_factory=asyncio.Event)
    tasks: list[asyncio.Task[Any]] = field(default_factory=list)
    setpoint: dict[str, Any] = field(default_factory=dict)
    # doorbell thread <-> reader task
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    wake_pending: bool = False
    thread_stop: threading.Event = field(default_factory=threading.Event)
    thread: threading.Thread | None = None
    last_state_key: tuple[Any, ...] | None = None
    last_status: chmod.Status | None = None
    last_missed: int = 0
    telemetry_sent: int = 0
    telemetry_lost: int = 0
    logging: loglive.RunLogging | None = None  # host log writer, live rerun (run_logging.py sets it)
    log_timing: bool = False  # the loop logs per-cycle timing (XRF_LOG_TIMING=1)
    guest: GuestReport | None = None  # which protection layers of the run sandbox hold
    watcher: SafetyWatcher | None = None  # the C thread that makes the outputs safe (safety.py)
    watch: WatchResult | None = None  # what it did, once it acted
    end_reason: str = ""  # set by whoever ends the run on purpose (runs.END_REASONS)

    @property
    def alive(self) -> bool:
        return self.proc.returncode is None


class Supervisor:
    def __init__(self, settings: Settings, hub: Hub, store: RunStore) -> None:
        self.settings = settings
        self.hub = hub
        self.store = store
        self.catalog = BuildCatalog(settings, hub.publish)
        self.guests = GuestSpawner(settings)
        self.current: Run | None = None
        self.last_row: RunRow | None = None
        # Held while a run starts, and by anything else that needs the bench to itself (the
        # FPGA self-check holds it for its whole duration, so no run can start meanwhile).
        self.bench_lock = asyncio.Lock()
        # What reacts to a run starting, its telemetry and its end (host logging, the 3D view,
        # the lease, the ROS bridge): registered by the app at start-up, told in order.
        self.lifecycle = RunLifecycle()
        # Runs a previous appliance process left live (it was killed or died): recover_orphans()
        # closes them once the event loop runs.
        self._orphans = list(store.orphans)

    async def recover_orphans(self) -> None:
        """Close the runs a dead appliance left behind: pick up the loop's log ring where it was
        left, stop the loop (it paused or stopped itself: host_timeout_action), and record its
        real counts and what happened. Each orphan keeps the bench lock until it is closed."""
        orphans, self._orphans = self._orphans, []
        for row in orphans:
            async with self.bench_lock:
                try:
                    await self._recover(row)
                except Exception:  # one bad record must not keep the appliance from serving
                    log.exception("run %s: recovering the orphaned run failed", row.id)
                    launcher = self._orphan_launcher(row)
                    if launcher:  # whatever failed, the loop does not run on unsupervised
                        with contextlib.suppress(ProcessLookupError):
                            os.kill(launcher, signal.SIGKILL)
                    if row.shm:
                        remove_shm(row.shm)

    def _orphan_launcher(self, row: RunRow) -> int:
        """The launcher of an orphaned run's loop, only if it really is this run's launcher (its
        XRF_RUN_DIR names the run folder); 0 if there is none. ``row.pid`` is the controller; its
        parent is the sandbox's init (guest._init) or, without a PID namespace, the launcher
        itself, which runs as our own uid in every sandbox mode (so its environ is ours to read)."""
        want = f"XRF_RUN_DIR={row.run_dir}".encode()
        found, pid = 0, row.pid or 0
        for _ in range(2):  # the init, then the launcher above it: the topmost that matches
            pid = _parent_of(pid) if pid else 0
            if pid <= 1 or not row.run_dir:
                break
            try:
                environ = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
            except OSError:
                continue  # the init, as the loop's user, may not be ours to read; its parent is
            if want in environ:
                found = pid
        return found

    async def _recover(self, row: RunRow) -> None:
        ch: Channels | None = None
        if row.shm:
            with contextlib.suppress(Exception):
                ch = await asyncio.to_thread(Channels.open, row.shm, 0.2)
        writer = None
        if ch is not None and row.run_dir and Path(row.run_dir).is_dir():
            # The ring's read position lives in the shared memory: a new writer goes on where the
            # dead appliance stopped, appending a segment to the same file.
            identity = {"project": row.build, "build": row.build, "run": str(row.id)}
            writer = loglive.HostLogWriter(ch, identity, Path(row.run_dir))
            last_seq = await asyncio.to_thread(_last_logged_seq, ch, Path(row.run_dir))
            if last_seq is not None:
                writer.skip_through(last_seq)  # written by the dead appliance, not yet released
            writer.start()
        before = ch.status() if ch is not None else None
        launcher = self._orphan_launcher(row)
        stopped_at = 0.0
        if launcher:
            log.warning("run %s: stopping loop pid %s left by a previous appliance", row.id, row.pid)
            for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(launcher, sig)
                deadline = time.monotonic() + self.settings.signal_timeout_s
                while _alive(launcher) and time.monotonic() < deadline:
                    await asyncio.sleep(0.02)
                if not _alive(launcher):
                    break
            stopped_at = time.time()
        stats = await asyncio.to_thread(writer.finish) if writer is not None else None
        last = before
        if ch is not None:
            with contextlib.suppress(ChannelsError):
                last = ch.status()
        records = 0
        if stats is not None:
            from ..logs.reader import open_log

            for path in dict.fromkeys(stats.files):  # the old appliance's segments and ours
                with contextlib.suppress(Exception):
                    records += len(open_log(path))
        parts = ["the appliance stopped while this run was live"]
        if ch is not None and last is not None:
            lost_at = ch.shm.host_heartbeat_ns
            if lost_at:
                ago = (time.monotonic_ns() - int(lost_at)) / 1e9
                parts.append(
                    f"its last heartbeat was at {time.strftime('%H:%M:%S', time.localtime(time.time() - ago))}"
                )
            if last.host_lost:
                parts.append(
                    f"the loop then did what host_timeout_action says "
                    f"({self.settings.host_timeout_action} after {self.settings.host_timeout_ms} ms)"
                )
        if stopped_at:
            parts.append(
                f"the restarted appliance stopped it at {time.strftime('%H:%M:%S', time.localtime(stopped_at))}"
            )
        elif row.pid and not _alive(row.pid):
            parts.append("the loop had already ended")
        values: dict[str, Any] = {
            "status": "crashed",
            "crashed": 1,
            "crash_reason": "appliance",
            "end_reason": "appliance_restart",
            "message": "; ".join(parts),
            "ended": stopped_at or row.ended or time.time(),
        }
        if last is not None:
            values.update(state=last.state_name, cycles=last.cycles, misses=last.missed)
        if stats is not None:
            values.update(log_records=records, log_lost=stats.lost + stats.unwritten, log_note=stats.failed)
        self.last_row = self.store.update(row.id, **values)
        if row.shm:
            remove_shm(row.shm)
        await self.lifecycle.ended(self.last_row, None)
        self.hub.publish(
            "alarm",
            {"kind": "crash", "end_reason": "appliance_restart", "run_id": row.id, "message": self.last_row.message},
        )
        self.hub.publish("run", {"event": "ended", "run": self.last_row.as_dict(), "active": False})

    # -- queries ------------------------------------------------------------------------------

    def bench(self) -> dict[str, Any]:
        real = self.settings.bench_is_real()
        return {
            "mode": "real" if real else "sim",
            "sim": "" if real else self.settings.sim,
            "profile": "ico-board over EVL spidev" if real else f"simulated ico board + {self.settings.sim} plant",
            "evl": Path("/dev/evl").exists(),
            "spidev": Path(self.settings.spi_device).exists(),
            "telemetry_hz": self.settings.telemetry_hz,
        }

    def run_payload(self, run: Run | None = None, event: str = "current") -> dict[str, Any]:
        run = run or self.current
        row = run.row if run else self.last_row
        payload: dict[str, Any] = {
            "event": event,
            "run": row.as_dict() if row else None,
            "active": bool(run and run.alive),
        }
        if run and run.channels is not None:
            info = run.channels.info
            payload.update(
                program=info["program"],
                cycle_freq=info["cycle_freq"],
                backend=info["backend"],
                transport=info["transport"],
                ros2xeno=schema_fields(info["ros2xeno_schema"]),
                xeno2ros=schema_fields(info["xeno2ros_schema"]),
                setpoint=run.setpoint,
            )
        if run and run.guest is not None:
            payload["confinement"] = run.guest.as_dict()
        return payload

    def state_payload(self, run: Run | None = None) -> dict[str, Any]:
        run = run or self.current
        if run is None or run.channels is None or run.last_status is None:
            return {
                "run_id": run.row.id if run else None,
                "active": False,
                "state": 0,
                "name": "NO RUN",
                "allowed": [],
                "rejected": None,
                "last_error": 0,
            }
        s = run.last_status
        rejected = None
        if s.cmd_rejected:
            rejected = {
                "ticket": s.cmd_rejected,
                "cmd": s.last_rejected_cmd,
                "name": chmod.command_name(s.last_rejected_cmd),
                "reason": s.reject_reason,
            }
        alive = run.alive and s.running
        return {
            "run_id": run.row.id,
            "active": alive,
            "state": s.state,
            "name": s.state_name,
            "allowed": chmod.allowed_commands(s.state) if alive else [],
            "rejected": rejected,
            "last_error": s.last_error,
            "cycles": s.cycles,
        }

    def snapshot(self) -> list[tuple[str, dict[str, Any]]]:
        return [("run", self.run_payload()), ("state", self.state_payload())]

    # -- starting -----------------------------------------------------------------------------

    async def start_run(
        self,
        build: str,
        sim: str | None = None,
        max_cycles: int | None = None,
        owner: str = "",
        log_timing: bool = False,
    ) -> RunRow:
        """`owner`: username of who starts it (auth.owns() decides who may see the run).
        `log_timing`: the loop logs every cycle's stage timing (cycle_timing.xrf in the run)."""
        async with self.bench_lock:
            if self.current is not None and not self.current.ended.is_set():
                raise SupervisorError(f"run {self.current.row.id} is still active; stop it first")
            entry = await self.catalog.ensure_built(build)
            assert entry.executable is not None
            plant = sim or entry.sim
            if plant not in plants.names():
                raise SupervisorError(f"unknown simulated plant {plant!r}; have: {', '.join(plants.names())}", 422)
            row = self.store.create(build, plant, "", "")
            if owner:
                row = self.store.update(row.id, owner=owner)
            shm_dir = self.guests.shm_dir_for(f"xrf-lab-{os.getpid()}-{row.id}")
            shm = f"{shm_dir.name}/{guest.SHM_NAME}"  # the host's path below /dev/shm
            run_dir = self.settings.runs_dir / str(row.id)
            run_dir.mkdir(parents=True, exist_ok=True)
            row = self.store.update(row.id, shm=shm, run_dir=str(run_dir))

            # An allow-list, never a copy of our own environment (xrflab.guest.ENV_ALLOWED).
            env = {
                "PATH": "/usr/local/bin:/usr/bin:/bin",
                "LANG": "C.UTF-8",
                "HOME": str(run_dir),
                "TMPDIR": "/tmp",
                "XRF_SHM": guest.SHM_NAME,
                "XRF_SIM": plant,
                "XRF_LOG_DIR": str(run_dir),
                "XRF_HOST_TIMEOUT_MS": str(self.settings.host_timeout_ms),
                "XRF_HOST_TIMEOUT_ACTION": self.settings.host_timeout_action,
                # We read monitor lines from the ring; the process echoing them to stdout as well
                # would show every line twice in the console.
                "XRF_QUIET": "1",
            }
            env.update(loglive.loop_env(row.id, build, log_timing))
            if not self.settings.bench_is_real():
                env["XRF_TRANSPORT"] = "sim"
            if max_cycles:
                env["XRF_MAX_CYCLES"] = str(max_cycles)
            env.update({k: v for k, v in self.settings.loop_env.items() if k in guest.ENV_ALLOWED})
            try:
                self.guests.prepare_dirs(run_dir, shm_dir)
                # Output goes to a file, not a pipe to us: if the appliance dies, a pipe would
                # turn the loop's next printf into SIGPIPE; a file keeps it running, and kept.
                with open(run_dir / "output.txt", "ab") as output:
                    proc, report = await self.guests.spawn(
                        entry.executable,
                        run_dir,
                        shm_dir,
                        env,
                        [entry.executable.parent],
                        output,
                        tag=shm,
                        timeout_s=self.settings.open_timeout_s,
                    )
            except (OSError, ValueError, RuntimeError, asyncio.TimeoutError) as exc:
                shutil.rmtree(shm_dir, ignore_errors=True)
                self.store.update(
                    row.id, status="failed", end_reason="start_failed", ended=time.time(), message=f"sandbox: {exc}"
                )
                raise SupervisorError(f"cannot start {entry.executable.name} in its sandbox: {exc}", 500) from exc
            if report.error:
                await proc.wait()
                shutil.rmtree(shm_dir, ignore_errors=True)
                self.last_row = self.store.update(
                    row.id,
                    status="failed",
                    end_reason="start_failed",
                    ended=time.time(),
                    message=f"sandbox: {report.error}",
                )
                self.hub.publish(
                    "alarm",
                    {"kind": "confinement", "run_id": row.id, "message": report.error, "missing": report.missing},
                )
                raise SupervisorError(f"the controller was not started: {report.error}", 503)
            if report.layers.get("mount"):
                # No mount namespace (allowed by an educator): the loop's /dev/shm is the host's.
                shm = guest.unconfined_shm_name(str(shm_dir))
                row = self.store.update(row.id, shm=shm)
            # The controller's own pid (what `kill` or a test would aim at); we wait on the launcher.
            row = self.store.update(row.id, pid=report.pid or proc.pid, status="starting")
            run = Run(row=row, proc=proc, shm=shm, run_dir=run_dir, build=entry, log_timing=log_timing, guest=report)
            self.current = run
            if report.missing:
                self.hub.publish(
                    "alarm",
                    {
                        "kind": "confinement",
                        "run_id": row.id,
                        "missing": report.missing,
                        "message": "the controller runs WITHOUT: "
                        + "; ".join(f"{k} ({v})" for k, v in report.missing.items()),
                    },
                )
            run.tasks.append(asyncio.create_task(self._watch_exit(run), name=f"run{row.id}-exit"))
            run.tasks.append(asyncio.create_task(self._pipe_output(run), name=f"run{row.id}-output"))

            opened = await self._open_channels(run)
            if not opened:
                await run.ended.wait()
                assert self.last_row is not None
                return self.last_row
            info = run.channels.info if run.channels else {}
            self._start_watcher(run)
            run.row = self.store.update(
                row.id, status="running", program=info.get("program", ""), cycle_freq=info.get("cycle_freq", 0)
            )
            self.lifecycle.started(run)  # host logging first: the log writer starts draining now
            run.tasks.append(asyncio.create_task(self._supervise(run), name=f"run{row.id}-heartbeat"))
            run.tasks.append(asyncio.create_task(self._guarded(self._reader, run), name=f"run{row.id}-reader"))
            run.tasks.append(asyncio.create_task(self._guarded(self._timing, run), name=f"run{row.id}-timing"))
            run.tasks.append(asyncio.create_task(self._disk_guard(run), name=f"run{row.id}-disk"))
            run.thread = threading.Thread(
                target=self._doorbell_thread,
                args=(run, asyncio.get_running_loop()),
                name=f"xrf-doorbell-{row.id}",
                daemon=True,
            )
            run.thread.start()
            self._refresh_state(run)
            self.hub.publish("run", self.run_payload(run, "started"))
            return run.row

    async def _guarded(self, body: Callable[[Run], Any], run: Run) -> None:
        """Restart a reader-type task after an unexpected error (a sample the codec cannot
        decode, say) instead of silently losing telemetry for the rest of the run."""
        while not run.ended.is_set():
            try:
                await body(run)
                return
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # reported to the dashboards, then carry on
                log.exception("run %s: %s failed", run.row.id, body.__name__)
                self.hub.publish(
                    "monitor",
                    {
                        "run_id": run.row.id,
                        "source": "appliance",
                        "lines": [{"text": f"appliance: {body.__name__} failed: {exc!r}"}],
                    },
                )
                await asyncio.sleep(0.5)

    async def _open_channels(self, run: Run) -> bool:
        """Map the run's shm once the loop marks it ready, unless the process dies first."""
        opening = asyncio.ensure_future(asyncio.to_thread(Channels.open, run.shm, self.settings.open_timeout_s))
        exited = asyncio.ensure_future(run.ended.wait())
        done, _ = await asyncio.wait({opening, exited}, return_when=asyncio.FIRST_COMPLETED)
        exited.cancel()
        if opening in done and opening.exception() is None:
            ch = opening.result()
            if run.ended.is_set():
                return False
            run.channels = ch
            ch.configure_host_timeout(self.settings.host_timeout_ms, self.settings.host_timeout_action)
            run.last_status = ch.status()
            return True
        if opening in done:  # the loop never made its shm ready: treat as a failed start
            message = f"loop did not open its shared memory: {opening.exception()}"
            run.row = self.store.update(run.row.id, message=message)
            await self._terminate(run)
        else:
            opening.add_done_callback(lambda f: f.exception())  # let the thread finish quietly
        return False

    # -- watching -----------------------------------------------------------------------------

    def _start_watcher(self, run: Run) -> None:
        """The safety watcher for a run whose shared memory is open (safety.py)."""
        ch = run.channels
        assert ch is not None
        info = ch.info
        # A slow loop (10 Hz) beats less often than the default timeout: a hang is three
        # missed periods at the least, never one long cycle.
        period_ms = 1000 // max(1, int(info.get("cycle_freq", 0)) or 1)
        hang_ms = max(self.settings.hang_timeout_ms, 3 * period_ms)
        # Below the loop's real-time priority, above everything else we run.
        loop_prio = int(info.get("priority", 0))
        prio = min(self.settings.watch_priority, loop_prio - 1) if loop_prio > 1 else self.settings.watch_priority
        real = self.settings.bench_is_real()
        try:
            w = SafetyWatcher(
                run.row.pid or run.proc.pid,
                ch,
                hang_timeout_ms=hang_ms,
                check_ms=max(2, min(20, hang_ms // 10)),
                force_sim=info.get("transport", "sim") == "sim",
                spi_device=self.settings.spi_device if real else "",
                rt_priority=max(0, prio),
            )
        except (OSError, ValueError) as exc:  # ESRCH: the loop is already gone; _watch_exit handles it
            log.warning("run %s: no safety watcher (%s); the event loop watches instead", run.row.id, exc)
            return
        run.watcher = w
        asyncio.get_running_loop().add_reader(w.fileno(), self._on_watch, run)

    def _on_watch(self, run: Run) -> None:
        """The watcher acted (outputs already safe): take note. The record follows the exit."""
        w = run.watcher
        if w is None:
            return
        with contextlib.suppress(ValueError, OSError):
            asyncio.get_running_loop().remove_reader(w.fileno())
        result = w.result()
        if result is not None:
            self._take_watch(run, result)

    def _take_watch(self, run: Run, result: WatchResult) -> None:
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

    async def _watch_exit(self, run: Run) -> None:
        returncode = await run.proc.wait()
        if run.watcher is not None:
            w = run.watcher
            with contextlib.suppress(ValueError, OSError):
                asyncio.get_running_loop().remove_reader(w.fileno())
            # The exit has happened: stop() lets the thread handle it first if it has not yet.
            self._take_watch(run, await asyncio.to_thread(w.stop))
        if not run.exited_at:
            run.exited_at = time.monotonic()
        self._safe_state(run)
        await self._finish(run, returncode)

    def _safe_state(self, run: Run) -> None:
        """Outputs off where no watcher did it (the loop died before its memory was open, or the
        watcher could not start)."""
        if run.safe_state:
            return
        transport = run.channels.info.get("transport", "sim") if run.channels else ""
        if run.channels is not None and transport == "sim":
            run.channels.force_sim_outputs_off()
            run.safe_state = "sim outputs forced off"
        elif self.settings.bench_is_real():
            run.safe_state = fpga_reset(self.settings.spi_device)
        else:
            # The simulated board lives inside the loop process: with no shm it died with it.
            run.safe_state = "simulated board ended with the process"
        run.safe_at = time.monotonic()

    async def _finish(self, run: Run, returncode: int) -> None:
        # Stop everything that touches the mapping before letting go of it.
        run.thread_stop.set()
        if run.thread is not None:
            await asyncio.to_thread(run.thread.join, 1.0)
        # Host logging drains the rest of the log ring (even after a crash) and records its counts
        # before the record says how the run ended (lifecycle.py: on_exited).
        await self.lifecycle.exited(run)
        current = asyncio.current_task()
        for task in run.tasks:
            if task is not current and task.get_name().endswith(("heartbeat", "reader", "timing", "disk")):
                task.cancel()
        status: chmod.Status | None = None
        if run.channels is not None:
            with contextlib.suppress(ChannelsError):
                status = run.channels.status()
        if status is not None:
            run.last_status = status
        exit_signal = -returncode if returncode < 0 else None
        exit_code = returncode if returncode >= 0 else None
        last = status or run.last_status
        end_reason, crashed, crash_reason = self._end_reason(run, returncode, last)
        how = f"signal {signal.Signals(exit_signal).name}" if exit_signal else f"exit status {exit_code}"
        if run.row.message:
            message = run.row.message
        elif end_reason == "hang":
            message = f"loop hung (no cycle for > {self.settings.hang_timeout_ms} ms), killed"
        elif end_reason == "self_exit":
            state = last.state_name if last else "?"
            message = f"the controller ended by itself in {state} ({how}) without a stop or quit"
        else:
            message = f"loop process ended with {how} ({END_REASONS[end_reason]})"
        safe_ms = (run.safe_at - run.exited_at) * 1000 if run.exited_at and run.safe_at >= run.exited_at else 0.0
        run.row = self.store.update(
            run.row.id,
            ended=time.time(),
            status="crashed" if crashed else ("ended" if run.channels is not None else "failed"),
            crashed=int(crashed),
            crash_reason=crash_reason,
            end_reason=end_reason,
            exit_code=exit_code,
            exit_signal=exit_signal,
            state=last.state_name if last else "",
            cycles=last.cycles if last else 0,
            misses=last.missed if last else 0,
            message=f"{message}; {run.safe_state}"
            + (f" {safe_ms:.1f} ms after exit" if crashed and not run.hang else ""),
        )
        # The record is final: the observers in order (lifecycle.py), then the browsers.
        await self.lifecycle.ended(run.row, run)
        remove_shm(run.shm)
        # No explicit unmap: a worker thread may still hold the Channels (a command wait); the
        # mapping goes with the last reference, and the name is already unlinked.
        self.last_row = run.row
        if crashed:
            self.hub.publish(
                "alarm",
                {
                    "kind": "hang" if run.hang else "crash",
                    "end_reason": end_reason,
                    "run_id": run.row.id,
                    "message": run.row.message,
                    "exit_code": exit_code,
                    "exit_signal": exit_signal,
                    "safe_state": run.safe_state,
                    # From the safety watcher (CLOCK_MONOTONIC ns): when it saw the exit or hang and
                    # when the outputs were safe; 0 where no watcher ran.
                    "event_ns": run.watch.event_ns if run.watch else 0,
                    "safe_ns": run.watch.safe_ns if run.watch else 0,
                    "heartbeat_ns": run.watch.heartbeat_ns if run.watch else 0,  # the loop's last cycle start
                    "watcher_rt": bool(run.watch and run.watch.rt_status == 0),
                },
            )
        run.ended.set()
        self.hub.publish("run", self.run_payload(run, "ended") | {"active": False})
        self.hub.publish("state", self.state_payload(run) | {"active": False, "allowed": []})
        # Let go of the run's tasks and log writer now: a cancelled task's traceback holds its
        # frames, whose locals hold the run's 10 MB mapping; left to the cyclic GC, a lab day of
        # crashes kept dozens of them (and their descriptors) alive.
        run.tasks.clear()
        run.logging = None

    def _end_reason(self, run: Run, returncode: int, last: chmod.Status | None) -> tuple[str, bool, str]:
        """(end_reason, crashed, crash_reason) of a run whose process ended with `returncode`;
        the names are runs.END_REASONS."""
        exit_signal = -returncode if returncode < 0 else 0
        loop_end = last.end_reason if last else chmod.lib.XRF_END_NONE
        if run.hang:
            return "hang", True, "hang"
        if run.end_reason:  # decided by whoever ended it (disk guard, shutdown, another user)
            return run.end_reason, False, ""
        if run.stop_requested and (returncode == 0 or exit_signal in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL)):
            return "stopped", False, ""
        if returncode != 0:
            return "crash", True, "signal" if exit_signal else "exit"
        if loop_end == chmod.lib.XRF_END_QUIT:
            return "quit", False, ""
        if loop_end == chmod.lib.XRF_END_CYCLE_LIMIT:
            return "cycle_limit", False, ""
        if loop_end == chmod.lib.XRF_END_SIGNAL:
            return "signal_stop", False, ""
        if loop_end == chmod.lib.XRF_END_RETURNED:
            return "returned", False, ""
        # exit(0) without leaving loop(): after STOP that is a program that simply ended; in any
        # other state (RUN above all) the controller walked away from a live machine.
        if last is not None and last.state in (STATE_STOPPED, chmod.lib.XRF_STATE_QUIT):
            return "returned", False, ""
        if run.channels is None:
            return "start_failed", False, ""
        return "self_exit", True, "self_exit"

    async def _pipe_output(self, run: Run) -> None:
        """Follow the loop's stdout/stderr file into the monitor console. Polled every 100 ms:
        this is for people reading, nothing safety-related waits on it."""
        pending = b""
        with open(run.run_dir / "output.txt", "rb") as f:
            while True:
                alive = run.alive  # sampled before reading, so the last output is not missed
                chunk = f.read(65536)
                if chunk:
                    *lines, pending = (pending + chunk).split(b"\n")
                    self.hub.publish(
                        "monitor",
                        {
                            "run_id": run.row.id,
                            "source": "stdout",
                            "lines": [{"text": line.decode("utf-8", "replace")} for line in lines],
                        },
                    )
                elif not alive:
                    if pending:
                        self.hub.publish(
                            "monitor",
                            {
                                "run_id": run.row.id,
                                "source": "stdout",
                                "lines": [{"text": pending.decode("utf-8", "replace")}],
                            },
                        )
                    return
                else:
                    await asyncio.sleep(0.1)

    async def _supervise(self, run: Run) -> None:
        """Host heartbeat out, loop heartbeat in (hang detection)."""
        ch = run.channels
        assert ch is not None
        hang_ns = self.settings.hang_timeout_ms * 1_000_000
        last_good = time.monotonic_ns()
        while run.alive:
            ch.host_heartbeat()
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
            if run.watcher is None and now - last_good > hang_ns and run.alive:
                run.hang = True
                self._safe_state(run)
                run.exited_at = time.monotonic()
                with contextlib.suppress(ProcessLookupError):
                    run.proc.send_signal(signal.SIGKILL)
                return
            await asyncio.sleep(min(self.settings.host_heartbeat_period_s, self.settings.hang_timeout_ms / 4000))

    async def _disk_guard(self, run: Run) -> None:
        """The run folder's disk use stays under the sandbox's limit: beyond it the run is stopped
        (the controller's own files; the appliance's log writer has its own full-disk handling)."""
        limit = self.guests.limits.run_dir_mb << 20
        while run.alive and not run.ended.is_set():
            await asyncio.sleep(2.0)
            used = await asyncio.to_thread(_folder_bytes, run.run_dir)
            if used > limit and run.alive:
                message = f"the run folder holds {used >> 20} MB, over the limit of {limit >> 20} MB: run stopped"
                run.row = self.store.update(run.row.id, message=message)
                self.hub.publish("alarm", {"kind": "disk", "run_id": run.row.id, "message": message})
                run.stop_requested = True
                run.end_reason = "disk"
                await self._terminate(run)
                return

    def _doorbell_thread(self, run: Run, loop: asyncio.AbstractEventLoop) -> None:
        """Blocks in the futex wait so the event loop never polls; wakes the reader task."""
        ch = run.channels
        assert ch is not None
        seen = ch.doorbell
        while not run.thread_stop.is_set():
            seen = ch.wait_doorbell(seen, DOORBELL_WAIT_MS)
            if not run.wake_pending:  # coalesce: one pending wake-up is enough
                run.wake_pending = True
                try:
                    loop.call_soon_threadsafe(run.wake.set)
                except RuntimeError:  # event loop closed (shutdown)
                    return

    async def _reader(self, run: Run) -> None:
        ch = run.channels
        assert ch is not None
        telemetry = ch.telemetry_reader()
        monitor = ch.monitor_reader()
        period_ns = int(1e9 / self.settings.telemetry_hz) if self.settings.telemetry_hz > 0 else 0
        next_due_ns = 0
        run_id = run.row.id
        while True:
            await run.wake.wait()
            run.wake.clear()
            run.wake_pending = False
            samples = telemetry.read()
            if samples:
                self.lifecycle.samples(run, samples)
            t0 = ch.status().t_start_ns if samples else 0
            for sample in samples:
                # Credit-based decimation: the average rate is telemetry_hz exactly even when the
                # loop's own rate is not a multiple of it (100 Hz -> 30 Hz sends 3 of every 10).
                if period_ns:
                    if sample.t_ns < next_due_ns:
                        continue
                    next_due_ns = max(next_due_ns + period_ns, sample.t_ns - period_ns)
                run.telemetry_sent += 1
                self.hub.publish(
                    "telemetry",
                    {
                        "run_id": run_id,
                        "cycle": sample.cycle,
                        "t_ns": sample.t_ns,
                        "t": (sample.t_ns - t0) / 1e9 if t0 else sample.t_ns / 1e9,
                        "state": sample.state,
                        "enc": sample.enc,
                        "din": sample.din,
                        "pwm": sample.pwm,
                        "dout": sample.dout,
                        "xeno2ros": sample.xeno2ros,
                        "ros2xeno_t_sent_ns": sample.ros2xeno_t_sent_ns,
                        "lost": telemetry.lost,
                    },
                )
            lines = monitor.read()
            if lines:
                self.hub.publish(
                    "monitor",
                    {
                        "run_id": run_id,
                        "source": "monitor",
                        "lines": [{"cycle": m.cycle, "t_ns": m.t_ns, "text": m.text} for m in lines],
                        "lost": monitor.lost,
                    },
                )
            self._refresh_state(run)

    def _refresh_state(self, run: Run) -> None:
        """Publish `state` when the state, a rejection, or liveness changed."""
        if run.channels is None:
            return
        with contextlib.suppress(ChannelsError):
            run.last_status = run.channels.status()
        s = run.last_status
        if s is None:
            return
        key = (s.state, s.cmd_rejected, s.running, s.last_error, run.alive)
        if key != run.last_state_key:
            run.last_state_key = key
            self.hub.publish("state", self.state_payload(run))

    async def _timing(self, run: Run) -> None:
        ch = run.channels
        assert ch is not None
        while True:
            await asyncio.sleep(self.settings.timing_period_s)
            try:
                s = ch.status()
                hists = ch.histograms()
            except ChannelsError:
                continue
            stages = {
                name: {
                    "count": h.count,
                    "min": h.min,
                    "max": h.max,
                    "mean": h.mean,
                    "p50": h.percentile(50),
                    "p99": h.percentile(99),
                }
                for name, h in hists.items()
            }
            wake = hists.get("wakeup")
            self.hub.publish(
                "timing",
                {
                    "run_id": run.row.id,
                    "cycles": s.cycles,
                    "misses": s.missed,
                    "cycle_freq": ch.info["cycle_freq"],
                    "stages": stages,
                    "jitter": {"edges": wake.edges, "counts": wake.counts} if wake else {"edges": [], "counts": []},
                    # every stage's histogram (non-empty buckets: lower edge ns, count), for tools
                    "histograms": {name: {"edges": h.edges, "counts": h.counts} for name, h in hists.items()},
                    "telemetry_sent": run.telemetry_sent,
                    "log_lost": s.log_lost,
                    "host_lost": s.host_lost,
                },
            )
            if s.missed > run.last_missed:
                self.hub.publish(
                    "alarm",
                    {
                        "kind": "deadline_miss",
                        "run_id": run.row.id,
                        "misses": s.missed,
                        "new": s.missed - run.last_missed,
                        "message": f"{s.missed - run.last_missed} deadline miss(es) in the last second ({s.missed} in total)",
                    },
                )
                run.last_missed = s.missed

    # -- controlling --------------------------------------------------------------------------

    def _active(self) -> Run:
        run = self.current
        if run is None or not run.alive or run.ended.is_set():
            raise SupervisorError("no run is active; start one first")
        if run.channels is None:
            raise SupervisorError("the run is still starting")
        return run

    async def command(self, cmd: str | int) -> chmod.CommandResult:
        """Queue a command, wait until the loop handled it, publish the state at once."""
        number = chmod.command_number(cmd)  # ValueError for unknown names
        run = self._active()
        ch = run.channels
        assert ch is not None
        ticket = ch.send_command(number, source=SOURCE_APPLIANCE)
        try:
            result = await asyncio.to_thread(ch.wait_command, ticket, 2.0)
        finally:
            if not run.ended.is_set():
                self._refresh_state(run)
        return result

    def setpoint(self, fields: dict[str, Any]) -> dict[str, Any]:
        """Merge into the run's Ros2Xeno (latest wins, so the whole message is written)."""
        run = self._active()
        ch = run.channels
        assert ch is not None
        merged = {**run.setpoint, **fields}
        ch.write_ros2xeno(merged)  # ValueError on unknown fields or bad values
        run.setpoint = merged
        return merged

    async def stop_current(self, by: str = "") -> RunRow:
        """Stop the active run in order. `by`: who asked (a username): someone other than the
        run's owner (an educator, a self-check) is named in the run's end."""
        run = self.current
        if run is None or run.ended.is_set():
            raise SupervisorError("no run is active")
        run.stop_requested = True
        if by and run.row.owner and by.strip().lower() != run.row.owner.strip().lower() and not run.end_reason:
            run.end_reason = "stopped_by_other"
            run.row = self.store.update(run.row.id, message=f"stopped by {by}")
        await self._graceful_stop(run)
        if not run.ended.is_set():
            await self._terminate(run)
        await run.ended.wait()
        return run.row

    async def _graceful_stop(self, run: Run) -> None:
        """stop (from RUN/PAUSED), then quit, each waiting for the loop to get there."""
        ch = run.channels
        if ch is None or not run.alive:
            return
        timeout = self.settings.stop_state_timeout_s
        try:
            state = await self._settled_state(run, timeout)
            if state in (STATE_RUN, STATE_PAUSED):
                ch.send_command("stop", source=SOURCE_APPLIANCE)
                state = await self._settled_state(run, timeout, want={STATE_STOPPED, STATE_ERROR})
            if state in (STATE_STOPPED, STATE_ERROR):
                ch.send_command("quit", source=SOURCE_APPLIANCE)
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(asyncio.shield(run.ended.wait()), timeout)
        except ChannelsError:
            pass  # command ring full or status locked: fall through to signals

    async def _settled_state(self, run: Run, timeout: float, want: set[int] | None = None) -> int:
        ch = run.channels
        assert ch is not None
        deadline = time.monotonic() + timeout
        while True:
            state = ch.status().state
            done = state in want if want else state not in SETTLING
            if done or time.monotonic() > deadline or not run.alive:
                return state
            await asyncio.sleep(0.005)

    async def _terminate(self, run: Run) -> None:
        """SIGINT (the runtime's safe stop), then SIGTERM, then SIGKILL."""
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            if not run.alive:
                break
            with contextlib.suppress(ProcessLookupError):
                run.proc.send_signal(sig)
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(asyncio.shield(run.ended.wait()), self.settings.signal_timeout_s)
            if run.ended.is_set():
                break

    async def shutdown(self) -> None:
        """Appliance stopping: end the run in order so the loop leaves its outputs off."""
        if self.current is not None and not self.current.ended.is_set():
            self.current.end_reason = self.current.end_reason or "shutdown"
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self.stop_current(), 15)
