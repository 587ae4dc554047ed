"""The bench self-check service (issue 6): the one check at a time, run in a worker thread, its
events to the dashboards. Its routes are server/http/selfcheck.py; the room's ``selfcheck``
command (room/commands.py) starts a check through the same service.

The check itself is ``xrflab.selfcheck.SelfCheck`` (the native ``xrf-selfcheck``, same IcoIo code
as the loop); every event the checker prints goes to the browsers as a ``selfcheck`` WebSocket
message: ``begin`` (published here: profile, transport, sim, faults) first, then the checker's own
events, and ``report`` last (the saved report, or ``error`` when the check could not run at all).

A check never runs over a loop: it takes the supervisor's start lock for its whole duration and
refuses while a run is active, unless asked to stop the run first. Refusals are xrflab.errors
kinds (Conflict, Invalid), answered by the one handler.

Made in the app's lifespan and handed to its users (it was made on first use inside the routes,
so the room imported a routes module to reach it).
"""

from __future__ import annotations

import asyncio
import atexit
import datetime as _dt
import itertools
import logging
import os
import threading
from dataclasses import dataclass, field
from typing import Any

from pydantic import BaseModel, Field
from starlette.requests import HTTPConnection

from . import profiles as profmod
from . import selfcheck as scmod
from .errors import Conflict, Invalid
from .server.security import audit
from .server.security.accounts import User
from .server.settings import Settings
from .server.ws.messages import SelfcheckMessage

log = logging.getLogger(__name__)

FAULTS_ENV = "XRF_SELFCHECK_FAULTS"


class StartCheck(BaseModel):
    profile: str = Field(description="a bench profile name from GET /api/profiles")
    stop_run: bool = Field(default=False, description="stop the active loop run first instead of refusing")
    faults: str | None = Field(
        default=None, max_length=200, description="simulated bench only: faults to inject, e.g. dead_encoder=2"
    )


@dataclass
class ActiveCheck:
    id: int
    profile: str
    transport: str
    sim: str
    faults: str
    user: str
    started: str
    check: scmod.SelfCheck | None = None
    events: list[dict[str, Any]] = field(default_factory=list)  # steps and the latest progress
    progress: dict[str, Any] | None = None
    abort_requested: bool = False

    def payload(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "profile": self.profile,
            "transport": self.transport,
            "sim": self.sim,
            "faults": self.faults,
            "user": self.user,
            "started": self.started,
            "steps": [e for e in self.events if e.get("event") == "step"],
            "progress": self.progress,
            "abort_requested": self.abort_requested,
        }


class SelfCheckService:
    """One per appliance: made in the app's lifespan (server/app.py), on app.state.selfcheck."""

    def __init__(self, settings: Settings, supervisor: Any) -> None:
        self.settings = settings
        self.supervisor = supervisor
        self.current: ActiveCheck | None = None
        self.last: dict[str, Any] | None = None  # {"check": id, "name": report name, "report": ...}
        self._ids = itertools.count(1)
        self._guard = asyncio.Lock()  # serialises starting
        atexit.register(self.abort)  # appliance exiting: the checker zeroes the outputs and exits

    def publish(self, payload: dict[str, Any]) -> None:
        """A self-check event to the dashboards: its fields are the checker's own (SelfcheckMessage
        keeps what it does not declare)."""
        self.supervisor.hub.publish(SelfcheckMessage.model_validate(payload))

    # -- the bench ------------------------------------------------------------------------------

    def bench(self) -> dict[str, Any]:
        """How a check reaches the board now: transport, simulated plant, device."""
        s = self.settings
        real = s.bench_is_real()
        if real:
            return {"mode": "real", "transport": "spidev", "sim": "", "device": s.spi_device}
        return {"mode": "sim", "transport": "sim", "sim": s.sim, "device": ""}

    def run_active(self) -> str | None:
        """A sentence when a loop run occupies the bench, else None."""
        run = self.supervisor.current
        if run is not None and not run.ended.is_set():
            row = run.row
            return f"a loop run is active (run {row.id}, {row.build}): stop the run first"
        return None

    def _busy(self) -> str | None:
        """bench_busy for SelfCheck (called in the worker thread)."""
        reason = self.run_active()
        if reason:
            return reason
        if self.settings.bench_is_real():
            # A loop started from a terminal (`xrf run`) on the default shared memory.
            return scmod.loop_active("xrf")
        return None

    # -- starting -------------------------------------------------------------------------------

    async def start(self, body: StartCheck, user: User, address: str) -> ActiveCheck:
        async with self._guard:
            if self.current is not None:
                raise Conflict(f"a self-check is already running (check {self.current.id}): wait for it or abort it")
            bench = self.bench()
            faults = (body.faults or "").strip()
            if bench["mode"] == "real":
                if faults:
                    raise Invalid("faults can only be injected on the simulated bench")
            elif not faults:
                faults = os.environ.get(FAULTS_ENV, "").strip()
            # Validate the profile before anything stops or moves.
            try:
                check = scmod.SelfCheck(
                    body.profile,
                    transport=bench["transport"],
                    sim=bench["sim"] or None,
                    faults=faults or None,
                    device=bench["device"] or None,
                    data_dir=self.settings.data_dir,
                    bench_busy=self._busy,
                    shm=None,
                )
            except profmod.ProfileError as exc:
                raise Invalid(str(exc), detail={"message": str(exc), "errors": field_errors(exc.problems)}) from None
            except scmod.SelfCheckError as exc:
                raise Invalid(str(exc)) from None

            start_lock = self.supervisor.bench_lock
            if start_lock is not None:
                try:
                    await asyncio.wait_for(start_lock.acquire(), 1.0)
                except asyncio.TimeoutError:
                    raise Conflict("a loop run is being started: stop the run first") from None
            try:
                reason = self.run_active()
                if reason and body.stop_run:
                    run_id = self.supervisor.current.row.id
                    await self.supervisor.stop_current(by=user.username)
                    audit.record(user, "run.stop", {"run": run_id, "why": "self-check"}, address)
                    reason = self.run_active()
                if reason:
                    raise Conflict(reason)
                active = ActiveCheck(
                    id=next(self._ids),
                    profile=check.profile.get("name", body.profile),
                    transport=check.transport,
                    sim=check.sim,
                    faults=check.faults,
                    user=user.username if user else "",
                    started=_now_iso(),
                    check=check,
                )
                self.current = active
            except BaseException:
                if start_lock is not None:
                    start_lock.release()
                raise
        audit.record(
            user,
            "selfcheck.start",
            {
                "check": active.id,
                "profile": active.profile,
                "transport": active.transport,
                "sim": active.sim,
                "faults": active.faults,
            },
            address,
        )
        self.publish(
            {
                "check": active.id,
                "event": "begin",
                "profile": active.profile,
                "transport": active.transport,
                "sim": active.sim,
                "faults": active.faults,
                "user": active.user,
                "started": active.started,
            }
        )
        loop = asyncio.get_running_loop()
        threading.Thread(
            target=self._work, args=(active, loop, start_lock), name=f"selfcheck-{active.id}", daemon=True
        ).start()
        return active

    def _work(self, active: ActiveCheck, loop: asyncio.AbstractEventLoop, start_lock: Any) -> None:
        """Worker thread: run the checker, forward its events, save the report."""
        check = active.check
        assert check is not None
        result: dict[str, Any] = {"check": active.id, "event": "report"}

        def forward(ev: dict[str, Any]) -> None:
            msg = {"check": active.id, **ev}
            loop.call_soon_threadsafe(self._on_event, active, msg)

        try:
            report = check.run(forward)
            try:
                path = scmod.save_report(report, data_dir=self.settings.data_dir)
                result.update(name=path.stem)
            except OSError as exc:
                result.update(name="", save_error=str(exc))
            result["report"] = report.as_dict()
        except scmod.BenchBusy as exc:
            result.update(event="error", message=str(exc))
        except Exception as exc:  # the checker could not start (build failed, ...)
            log.exception("self-check %s failed", active.id)
            result.update(event="error", message=f"the self-check could not run: {exc}")
        finally:
            loop.call_soon_threadsafe(self._finished, active, result, start_lock)

    def _on_event(self, active: ActiveCheck, msg: dict[str, Any]) -> None:
        if msg.get("event") == "progress":
            active.progress = msg
        else:
            active.events.append(msg)
        self.publish(msg)

    def _finished(self, active: ActiveCheck, result: dict[str, Any], start_lock: Any) -> None:
        if self.current is active:
            self.current = None
        if start_lock is not None and start_lock.locked():
            start_lock.release()
        self.last = result
        self.publish(result)

    def close(self) -> None:
        """The app is stopping: a check under way is aborted (the checker zeroes the outputs),
        and the exit hook of this service goes (one app after another in a test process)."""
        self.abort()
        atexit.unregister(self.abort)

    def abort(self) -> bool:
        active = self.current
        if active is None or active.check is None:
            return False
        active.abort_requested = True
        active.check.abort()
        return True


def selfcheck_of(conn: HTTPConnection) -> SelfCheckService:
    """FastAPI dependency: the app's self-check service (made in server/app.py's lifespan)."""
    svc: SelfCheckService = conn.app.state.selfcheck
    return svc


def _now_iso() -> str:
    return _dt.datetime.now().astimezone().isoformat(timespec="seconds")


def field_errors(problems: list[profmod.FieldError]) -> list[dict[str, str]]:
    """The validator's problems as JSON: [{"field": "channel 1.duty", "message": ...}, ...];
    the field comes from the validator itself (xrflab.profiles), '' for the profile as a whole."""
    return [p.as_dict() for p in problems]
