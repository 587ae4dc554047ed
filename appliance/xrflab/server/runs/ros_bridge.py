"""The ROS 2 bridge run by the appliance (issue 9, items 1 and 4): one ``xrf ros-bridge`` process
per loop run while the bridge is enabled, restarted with backoff if it dies while the run lives,
stopped (SIGTERM, then SIGKILL) when the run ends or the bridge is switched off. Its output goes
to ``runs/<id>/ros-bridge.txt``.

The bench lease for ROS 2 commands (the *gate*): the appliance listens on a Unix socket
(``<data>/ros-gate.sock``, mode 0600). Every bridge process gets a fresh random token in its
environment (``XRF_ROS_GATE_TOKEN``) and ``--gate-url unix:<socket>``; for every XenoCmd it sends
one JSON line ``{"token", "user", "cmd"}`` and gets ``{"allowed", "reason"}`` back. The token is
only good for the bridge process it was made for, while its run is the current one, and only
for this question (it is not an API token: the HTTP API does not know it).

The rule (docs/ros2/bridge.md, "Run by the appliance"): ``stop`` and ``pause`` follow the STOP
rule (any enabled student or educator account, without the lease); every other command needs the
bridge's user to *hold* the bench lease, educators included — the DDS domain is not
authenticated, so a ROS 2 command never gets more than the lease holder's say.

Status: ``status()`` (``GET /api/ros``) and a ``ros`` WebSocket message on every change.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import json
import logging
import os
import resource
import secrets
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from ... import channels as chmod
from ...runfolder import open_in
from ..security import audit
from ..ws.messages import RosMessage, ServerMessage
from .children import Child, spawn
from .lifecycle import RunObserver

log = logging.getLogger("xrflab.ros_supervisor")

TOPICS = ["XenoCmd", "XenoState", "Ros2Xeno", "Xeno2Ros"]
GATE_TOKEN_ENV = "XRF_ROS_GATE_TOKEN"
BRIDGE_OUTPUT = "ros-bridge.txt"  # the bridge's output, in the run's folder
BACKOFF_FIRST_S = 0.5
BACKOFF_MAX_S = 10.0
STABLE_AFTER_S = 30.0  # a bridge that ran this long starts the backoff afresh when it dies
_CAP_SYS_NICE = 23


def realtime_permitted(priority: int) -> tuple[bool, str]:
    """May a child of ours use SCHED_FIFO `priority`? (root, CAP_SYS_NICE or RLIMIT_RTPRIO)."""
    if priority <= 0:
        return False, "priority 0: normal scheduling"
    if os.geteuid() == 0:
        return True, ""
    try:
        soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
        if soft == resource.RLIM_INFINITY or soft >= priority:
            return True, ""
    except (ValueError, OSError, AttributeError):
        pass
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("CapEff:") and int(line.split()[1], 16) >> _CAP_SYS_NICE & 1:
                return True, ""
    except (OSError, ValueError, IndexError):
        pass
    return False, f"no CAP_SYS_NICE and RLIMIT_RTPRIO < {priority}: normal scheduling"


def _command_name(cmd: int) -> str:
    return next((name for name, n in chmod.COMMAND_NUMBERS.items() if n == cmd), str(cmd))


def _short_socket_path(preferred: Path) -> Path:
    # sun_path holds 108 bytes; a deep data folder (tests) gets a private temporary folder instead.
    if len(str(preferred).encode()) < 100:
        return preferred
    return Path(tempfile.mkdtemp(prefix="xrf-ros-")) / "gate.sock"


class BridgeProc:
    """One bridge process of one run (across its restarts)."""

    def __init__(self, run: Any, user: str) -> None:
        self.run = run
        self.user = user
        self.proc: Child | None = None
        self.token = ""
        self.stop = asyncio.Event()
        self.task: asyncio.Task[None] | None = None


class RosBridgeSupervisor(RunObserver):
    name = "ROS 2 bridge"

    def __init__(self, settings: Any, supervisor: Any, hub: Any, security: Any) -> None:
        self.settings = settings
        self.supervisor = supervisor
        self.hub = hub
        self.security = security
        self.enabled = bool(settings.ros_bridge)
        self.state = "stopped"  # running | stopped | failed
        self.pid: int | None = None
        self.run_id: int | None = None
        self.user = ""
        self.last_error = ""
        self.restarts = 0
        self.started_at: float | None = None
        self.priority, self.sched_note = self._priority()
        self.socket_path = _short_socket_path(Path(settings.data_dir) / "ros-gate.sock")
        self._server: asyncio.AbstractServer | None = None
        self._current: BridgeProc | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._lock = asyncio.Lock()
        self._pending: set[asyncio.Task[None]] = set()
        # Live tuning's service (xrflab/params/service.py), handed over by server/app.py: a bridge's
        # `ros2 param set` comes through the gate and is set there, as the dashboard's is.
        self.params: Any = None
        supervisor.lifecycle.register(self)  # one bridge per run: started and stopped with it

    def _priority(self) -> tuple[int, str]:
        wanted = int(self.settings.ros_bridge_priority)
        ok, why = realtime_permitted(wanted)
        return (wanted, f"SCHED_FIFO {wanted}") if ok else (0, why)

    # -- life cycle ---------------------------------------------------------------------------

    async def open(self) -> None:
        self._loop = asyncio.get_running_loop()
        with contextlib.suppress(FileNotFoundError):
            self.socket_path.unlink()
        self.socket_path.parent.mkdir(parents=True, exist_ok=True)
        old = os.umask(0o177)  # the socket is created 0600: only the appliance's user connects
        try:
            self._server = await asyncio.start_unix_server(self._serve_gate, path=str(self.socket_path))
        finally:
            os.umask(old)
        await self.reconcile()

    async def close(self) -> None:
        self.enabled = False
        await self._stop_current()
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 2)
        with contextlib.suppress(FileNotFoundError):
            self.socket_path.unlink()

    # -- run observer (server/runs/lifecycle.py): last in the list, after host logging and the lease --------

    def on_started(self, run: Any) -> None:
        if self._loop is not None:
            self._loop.call_soon_threadsafe(self._schedule_reconcile)

    async def on_ended(self, row: Any, run: Any) -> None:
        if self._loop is not None:
            self._loop.call_soon_threadsafe(self._schedule_reconcile)

    def _schedule_reconcile(self) -> None:
        task = asyncio.get_running_loop().create_task(self.reconcile())
        self._pending.add(task)  # a strong reference until it is done
        task.add_done_callback(self._pending.discard)

    async def set_enabled(self, enabled: bool) -> dict[str, Any]:
        self.enabled = bool(enabled)
        if not self.enabled:
            self.last_error = ""
        await self.reconcile()
        self._publish()
        return self.status()

    def _active_run(self) -> Any:
        run = self.supervisor.current
        if run is None or not run.alive or run.ended.is_set() or run.channels is None:
            return None
        return run

    async def reconcile(self) -> None:
        """Bring the bridge in line with (enabled, the active run)."""
        async with self._lock:
            run = self._active_run() if self.enabled else None
            cur = self._current
            if cur is not None and (run is None or cur.run is not run):
                await self._stop_current()
            if run is not None and self._current is None:
                user = self.settings.ros_bridge_user or run.row.owner or ""
                bp = BridgeProc(run, user)
                self._current = bp
                self.restarts = 0
                self.last_error = ""
                self.run_id, self.user = run.row.id, user
                bp.task = asyncio.create_task(self._keep(bp), name=f"run{run.row.id}-ros-bridge")
            self._publish()

    async def _stop_current(self) -> None:
        bp, self._current = self._current, None
        if bp is None:
            return
        bp.stop.set()
        if bp.task is not None:
            with contextlib.suppress(Exception, asyncio.CancelledError):
                await bp.task

    # -- one run's bridge ---------------------------------------------------------------------

    def _argv(self, bp: BridgeProc) -> list[str]:
        return [
            sys.executable,
            "-m",
            "xrflab.cli",
            "ros-bridge",
            "--shm",
            bp.run.shm,
            "--user",
            bp.user,
            "--priority",
            str(self.priority),
            "--gate-url",
            f"unix:{self.socket_path}",
        ]

    async def _spawn(self, bp: BridgeProc) -> Child:
        bp.token = secrets.token_urlsafe(32)
        package_root = str(Path(__file__).resolve().parents[3])  # appliance/, holding xrflab
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (package_root, env.get("PYTHONPATH", "")) if p)
        env[GATE_TOKEN_ENV] = bp.token
        env["XRF_USER"] = bp.user
        env.pop("XRF_BOOTSTRAP_ADMIN_PASSWORD", None)
        # In the run folder (the loop's to write too): through its helper, our own file only, so
        # a link the loop put there (to /etc/passwd, say) is refused, never appended to.
        try:
            fd = open_in(bp.run.run_dir, BRIDGE_OUTPUT, os.O_WRONLY | os.O_CREAT | os.O_APPEND, own=True)
        except ValueError as exc:
            raise OSError(str(exc)) from None
        with os.fdopen(fd, "ab") as out:
            out.write(
                f"--- {time.strftime('%Y-%m-%d %H:%M:%S')} xrf ros-bridge for user '{bp.user}' "
                f"({self.sched_note})\n".encode()
            )
            out.flush()
            # children.spawn, not asyncio's: under uvloop that would hand the bridge every
            # descriptor of the appliance that is not close-on-exec.
            return spawn(
                self._argv(bp),
                env=env,
                cwd=bp.run.run_dir,
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )

    async def _keep(self, bp: BridgeProc) -> None:
        backoff = BACKOFF_FIRST_S
        first = True
        while not bp.stop.is_set():
            if not first:
                self.restarts += 1
            first = False
            try:
                bp.proc = await self._spawn(bp)
            except OSError as exc:
                self._set("failed", None, f"cannot start the bridge: {exc}")
                return
            t0 = time.monotonic()
            self.started_at = time.time()
            self._set("running", bp.proc.pid, self.last_error)
            waiter = asyncio.ensure_future(bp.proc.wait())
            stopper = asyncio.ensure_future(bp.stop.wait())
            await asyncio.wait({waiter, stopper}, return_when=asyncio.FIRST_COMPLETED)
            stopper.cancel()
            if bp.stop.is_set():
                await self._terminate(bp.proc, waiter)
                bp.token = ""
                self._set("stopped", None, self.last_error)
                return
            rc = bp.proc.returncode
            bp.token = ""
            how = f"signal {signal.Signals(-rc).name}" if rc is not None and rc < 0 else f"exit status {rc}"
            reason = self._last_line(bp) or how
            if time.monotonic() - t0 >= STABLE_AFTER_S:
                backoff = BACKOFF_FIRST_S
            run_lives = bp.run.alive and not bp.run.ended.is_set()
            if not run_lives:
                self._set("stopped", None, "" if rc == 1 else f"ended with {how}")
                return
            self._set("failed", None, f"ended with {how}: {reason}; restarting in {backoff:g} s")
            log.warning("run %s: ROS 2 bridge %s; restarting in %g s", bp.run.row.id, how, backoff)
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(bp.stop.wait(), backoff)
            backoff = min(backoff * 2, BACKOFF_MAX_S)
        self._set("stopped", None, self.last_error)

    async def _terminate(self, proc: Child, waiter: asyncio.Future[int]) -> None:
        for sig, wait_s in ((signal.SIGTERM, self.settings.ros_bridge_stop_timeout_s), (signal.SIGKILL, 5.0)):
            if proc.returncode is not None:
                return
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(sig)
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(asyncio.shield(waiter), wait_s)

    @staticmethod
    def _last_line(bp: BridgeProc) -> str:
        try:
            with open(open_in(bp.run.run_dir, BRIDGE_OUTPUT, own=True), "rb") as f:
                f.seek(0, os.SEEK_END)
                f.seek(max(0, f.tell() - 4096))
                lines = [ln.strip() for ln in f.read(4096).decode("utf-8", "replace").splitlines() if ln.strip()]
        except (OSError, ValueError):
            return ""
        return lines[-1][:300] if lines else ""

    # -- status -------------------------------------------------------------------------------

    def _set(self, state: str, pid: int | None, error: str) -> None:
        self.state, self.pid, self.last_error = state, pid, error
        self._publish()

    def status(self) -> dict[str, Any]:
        run = self._current.run if self._current else None
        return {
            "enabled": self.enabled,
            "state": self.state,
            "pid": self.pid,
            "run_id": self.run_id,
            "user": self.user,
            "topics": TOPICS,
            "last_error": self.last_error,
            "restarts": self.restarts,
            "started": self.started_at if self.state == "running" else None,
            "scheduling": self.sched_note,
            "output": str(Path(run.run_dir) / BRIDGE_OUTPUT) if run is not None else "",
            "configured_user": self.settings.ros_bridge_user,
        }

    def message(self) -> RosMessage:
        """`status`, as the `ros` WebSocket message (messages.RosMessage)."""
        return RosMessage.model_validate(self.status())

    def _publish(self) -> None:
        self.hub.publish(self.message())

    def snapshot(self) -> list[ServerMessage]:
        return [self.message()]

    # -- the gate -----------------------------------------------------------------------------

    async def _serve_gate(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while True:
                try:
                    line = await asyncio.wait_for(reader.readline(), 30)
                except (asyncio.TimeoutError, ValueError):
                    break
                if not line:
                    break
                try:
                    req = json.loads(line)
                    if isinstance(req, dict) and "params" in req:
                        allowed, reason = await self.decide_params(
                            str(req.get("token", "")), str(req.get("user", "")), req["params"]
                        )
                    else:
                        allowed, reason = self.decide(
                            str(req.get("token", "")), str(req.get("user", "")), int(req.get("cmd"))
                        )
                except (ValueError, TypeError, AttributeError) as exc:
                    allowed, reason = False, f"bad gate request: {exc}"
                writer.write(json.dumps({"allowed": allowed, "reason": reason}).encode() + b"\n")
                await writer.drain()
        except (ConnectionError, OSError):
            pass
        finally:
            writer.close()

    def decide(self, token: str, user_name: str, cmd: int) -> tuple[bool, str]:
        """May the bridge holding `token` send `cmd` now? (allowed, reason)."""
        from ..security.auth import SAFE_COMMANDS, Perm, may

        bp = self._current
        if bp is None or not bp.token or not hmac.compare_digest(token.encode(), bp.token.encode()):
            return False, "unknown bridge (token not valid for the current run)"
        if user_name != bp.user:
            return False, f"this bridge acts for '{bp.user}', not '{user_name}'"
        name = _command_name(cmd)
        allowed, reason, user = self._rule(bp.user, cmd, name, SAFE_COMMANDS, Perm, may)
        audit.record(
            user, "command", {"cmd": name, "via": "ros", "allowed": allowed, "reason": reason, "run": bp.run.row.id}
        )
        return allowed, reason

    async def decide_params(self, token: str, user_name: str, values: Any) -> tuple[bool, str]:
        """A parameter set from the bridge holding `token` (`ros2 param set`): the bench holder's
        only (the rule of a non-safe command), then the parameter service's checks, all or nothing."""
        from ...errors import XrfError
        from ..security.auth import SAFE_COMMANDS, Perm, may

        bp = self._current
        if bp is None or not bp.token or not hmac.compare_digest(token.encode(), bp.token.encode()):
            return False, "unknown bridge (token not valid for the current run)"
        if user_name != bp.user:
            return False, f"this bridge acts for '{bp.user}', not '{user_name}'"
        if self.params is None:
            return False, "live tuning is not available"
        allowed, reason, user = self._rule(bp.user, 0, "param", SAFE_COMMANDS, Perm, may)
        audit.record(user, "params", {"via": "ros", "allowed": allowed, "reason": reason, "run": bp.run.row.id})
        if not allowed:
            return False, reason
        if not isinstance(values, dict):
            return False, "bad gate request: params is not an object"
        try:
            answer = await self.params.set(values, f"{bp.user} (ROS 2)")
        except XrfError as exc:
            return False, str(exc)
        return True, f"applied at cycle {answer['cycle']}"

    def _rule(self, user_name: str, cmd: int, name: str, safe: Any, perm: Any, may: Any) -> tuple[bool, str, Any]:
        accounts = self.security.accounts
        lease = self.security.lease
        user = accounts.by_name(user_name) if (accounts is not None and user_name) else None
        if user is None or user.disabled:
            return False, f"no enabled account '{user_name}' (set ros_bridge_user or start the run as a user)", user
        if name in safe:
            if may(user, perm.STOP):
                return True, f"{name} is always allowed (STOP rule)", user
            return False, f"{user.role}s may not {name} (STOP rule: students and educators)", user
        if user.must_change:
            return False, f"'{user.username}' must change the password first", user
        if lease is None:
            return False, "the bench lease is not available", user
        if lease.holds(user):
            lease.touch(user)  # driving from ROS 2 keeps the lease alive like driving from the dashboard
            return True, f"'{user.username}' holds the bench lease", user
        holder = lease.holder
        who = f"{holder.user.username} holds it" if holder else "nobody holds it; take it on the dashboard"
        return False, f"'{user.username}' does not hold the bench lease ({who})", user
