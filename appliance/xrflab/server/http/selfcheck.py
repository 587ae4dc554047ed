"""HTTP routes of the bench self-check (issue 6) and the bench-profile editor. Educators only.

The check itself is ``xrflab.selfcheck.SelfCheck`` (the native ``xrf-selfcheck``, same IcoIo code
as the loop). It runs in a worker thread, never on the event loop, one at a time; every event the
checker prints goes to the browsers as a WebSocket message of type ``selfcheck``::

    {"type": "selfcheck", "check": 3, "event": "begin"|"start"|"progress"|"step"|"end"|"error"|"report", ...}

``begin`` (published by the appliance: profile, transport, sim, faults) comes first, then the
checker's own events (see xrflab/selfcheck.py), and ``report`` last (the saved report, or
``error`` with ``message`` when the check could not run at all).

Where it runs: on the simulated bench, transport ``sim`` with the appliance's simulated plant
(``Settings.sim``); on a real bench, ``spidev`` on ``Settings.spi_device``. Faults can be injected
only on the simulated bench: ``faults`` in the request (practice for educators), else the
``XRF_SELFCHECK_FAULTS`` environment variable of the appliance (a hook for tests).

A check never runs over a loop: it takes the supervisor's start lock for its whole duration (a
run started meanwhile waits for the check to finish) and refuses while a run is active, unless
the request says ``stop_run`` (then the run is stopped in order first).
"""

from __future__ import annotations

import asyncio
import atexit
import datetime as _dt
import itertools
import logging
import os
import re
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from fastapi import APIRouter, Depends, HTTPException, Request
from fastapi.responses import Response
from pydantic import BaseModel, Field

from ... import profiles as profmod
from ... import selfcheck as scmod
from ..security import audit
from ..security.auth import Perm, User, client_address, current_user, requires
from ..ws.messages import SelfcheckMessage

log = logging.getLogger(__name__)

router = APIRouter(tags=["self-check"])

FAULTS_ENV = "XRF_SELFCHECK_FAULTS"
REPORT_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,120}$")
MAX_REPORTS_LISTED = 200


# ---- models -------------------------------------------------------------------------------------


class StartCheck(BaseModel):
    profile: str = Field(description="a bench profile name from GET /api/profiles")
    stop_run: bool = Field(default=False, description="stop the active loop run first instead of refusing")
    faults: str | None = Field(
        default=None, max_length=200, description="simulated bench only: faults to inject, e.g. dead_encoder=2"
    )


class ReportSummary(BaseModel):
    name: str = Field(description="the report's id (file name without .json)")
    bench: str
    verdict: str
    started: str
    duration_s: float
    transport: str
    sim: str
    faults: str
    outputs_zeroed: bool
    counts: dict[str, int]


# ---- the one self-check at a time ---------------------------------------------------------------


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
    """Hung on app.state.selfcheck (made on first use)."""

    def __init__(self, app: Any) -> None:
        self.app = app
        self.settings = app.state.settings
        self.current: ActiveCheck | None = None
        self.last: dict[str, Any] | None = None  # {"check": id, "name": report name, "report": ...}
        self._ids = itertools.count(1)
        self._guard = asyncio.Lock()  # serialises starting
        atexit.register(self.abort)  # appliance exiting: the checker zeroes the outputs and exits

    @property
    def supervisor(self) -> Any:
        return self.app.state.supervisor

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
                raise HTTPException(
                    409, f"a self-check is already running (check {self.current.id}): wait for it or abort it"
                )
            bench = self.bench()
            faults = (body.faults or "").strip()
            if bench["mode"] == "real":
                if faults:
                    raise HTTPException(422, "faults can only be injected on the simulated bench")
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
                raise HTTPException(422, {"message": str(exc), "errors": field_errors(exc.problems)}) from None
            except scmod.SelfCheckError as exc:
                raise HTTPException(422, str(exc)) from None

            start_lock = self.supervisor.bench_lock
            if start_lock is not None:
                try:
                    await asyncio.wait_for(start_lock.acquire(), 1.0)
                except asyncio.TimeoutError:
                    raise HTTPException(409, "a loop run is being started: stop the run first") from None
            try:
                reason = self.run_active()
                if reason and body.stop_run:
                    run_id = self.supervisor.current.row.id
                    await self.supervisor.stop_current(by=user.username)
                    audit.record(user, "run.stop", {"run": run_id, "why": "self-check"}, address)
                    reason = self.run_active()
                if reason:
                    raise HTTPException(409, reason)
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

    def abort(self) -> bool:
        active = self.current
        if active is None or active.check is None:
            return False
        active.abort_requested = True
        active.check.abort()
        return True


def service(request: Request) -> SelfCheckService:
    svc = getattr(request.app.state, "selfcheck", None)
    if svc is None:
        svc = request.app.state.selfcheck = SelfCheckService(request.app)
    return svc


def _now_iso() -> str:
    return _dt.datetime.now().astimezone().isoformat(timespec="seconds")


# ---- profile problems for the browser ----------------------------------------------------------


def field_errors(problems: list[profmod.FieldError]) -> list[dict[str, str]]:
    """The validator's problems as JSON: [{"field": "channel 1.duty", "message": ...}, ...];
    the field comes from the validator itself (xrflab.profiles), '' for the profile as a whole."""
    return [p.as_dict() for p in problems]


# ---- routes: the check --------------------------------------------------------------------------


@router.get("/api/selfcheck", dependencies=[requires(Perm.EDUCATOR)])
async def selfcheck_status(request: Request) -> dict[str, Any]:
    """What a check would use now, whether the bench is free, the check under way and the last result."""
    svc = service(request)
    return {
        "bench": svc.bench(),
        "run_active": svc.run_active(),
        "running": svc.current.payload() if svc.current else None,
        "last": svc.last,
    }


@router.post("/api/selfcheck", status_code=202, dependencies=[requires(Perm.EDUCATOR)])
async def selfcheck_start(body: StartCheck, request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    """Start a check. 409 while a loop run is active (unless stop_run) or another check runs;
    422 for a bad profile. Progress and the report arrive as `selfcheck` WebSocket messages."""
    active = await service(request).start(body, user, client_address(request))
    return active.payload()


@router.post("/api/selfcheck/abort", dependencies=[requires(Perm.EDUCATOR)])
async def selfcheck_abort(request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    """Abort the running check: the checker zeroes PWM and digital outputs and stops (the report
    says outputs_zeroed)."""
    svc = service(request)
    active = svc.current
    if not svc.abort():
        raise HTTPException(409, "no self-check is running")
    audit.record(user, "selfcheck.abort", {"check": active.id if active else None}, client_address(request))
    return {"aborting": active.id if active else None}


def _report_path(request: Request, name: str) -> Path:
    if not REPORT_NAME_RE.match(name) or ".." in name:
        raise HTTPException(404, "no such report")
    path = scmod.reports_dir(service(request).settings.data_dir) / f"{name}.json"
    if not path.is_file():
        raise HTTPException(404, "no such report")
    return path


@router.get("/api/selfcheck/reports", response_model=list[ReportSummary], dependencies=[requires(Perm.EDUCATOR)])
async def selfcheck_reports(request: Request) -> list[dict[str, Any]]:
    """Saved reports, newest first."""
    settings = service(request).settings

    def work() -> list[dict[str, Any]]:
        out = []
        for path in scmod.list_reports(data_dir=settings.data_dir)[:MAX_REPORTS_LISTED]:
            try:
                r = scmod.load_report(path)
            except (OSError, ValueError, TypeError, KeyError):
                continue
            out.append(
                {
                    "name": path.stem,
                    "bench": r.bench,
                    "verdict": r.verdict,
                    "started": r.started,
                    "duration_s": r.duration_s,
                    "transport": r.transport,
                    "sim": r.sim,
                    "faults": r.faults,
                    "outputs_zeroed": r.outputs_zeroed,
                    "counts": r.counts(),
                }
            )
        return out

    return await asyncio.to_thread(work)


@router.get("/api/selfcheck/reports/{name}", dependencies=[requires(Perm.EDUCATOR)])
async def selfcheck_report(name: str, request: Request) -> dict[str, Any]:
    path = _report_path(request, name)
    try:
        report = scmod.load_report(path)
    except (OSError, ValueError, TypeError, KeyError) as exc:
        raise HTTPException(500, f"cannot read the report: {exc}") from None
    return {"name": name, **report.as_dict()}


EXPORTS = {
    "json": ("application/json", "json"),
    "markdown": ("text/markdown; charset=utf-8", "md"),
    "text": ("text/plain; charset=utf-8", "txt"),
}


@router.get("/api/selfcheck/reports/{name}/export", dependencies=[requires(Perm.EDUCATOR)])
async def selfcheck_export(name: str, request: Request, fmt: Literal["json", "markdown", "text"] = "json") -> Response:
    """The report as a download: JSON, Markdown (a table to paste into a ticket) or plain text."""
    path = _report_path(request, name)
    try:
        text = scmod.export_report(scmod.load_report(path), fmt)
    except (OSError, ValueError, TypeError, KeyError) as exc:
        raise HTTPException(500, f"cannot read the report: {exc}") from None
    media, ext = EXPORTS[fmt]
    return Response(
        text, media_type=media, headers={"Content-Disposition": f'attachment; filename="selfcheck-{name}.{ext}"'}
    )


# ---- routes: bench profiles ---------------------------------------------------------------------


def _data_dir(request: Request) -> Path:
    return request.app.state.settings.data_dir


def _has_default(name: str) -> bool:
    return (profmod.DEFAULTS_DIR / f"{name}.json").is_file()


@router.get("/api/profiles", dependencies=[requires(Perm.EDUCATOR)])
async def profiles_list(request: Request) -> list[dict[str, Any]]:
    """Every bench profile by name; `source` is default (deploy/profiles) or edited (data folder)."""
    infos = profmod.list_profiles(_data_dir(request))
    return [{**i.as_dict(), "has_default": _has_default(i.name)} for i in infos]


def _check_name(name: str) -> None:
    if not profmod.NAME_RE.match(name):
        raise HTTPException(404, f"no bench profile named {name!r}")


@router.get("/api/profiles/{name}", dependencies=[requires(Perm.EDUCATOR)])
async def profile_get(name: str, request: Request) -> dict[str, Any]:
    _check_name(name)
    data_dir = _data_dir(request)
    try:
        path = profmod.find_profile(name, data_dir)
        profile = profmod.load_profile(path)
    except profmod.ProfileNotFound as exc:
        raise HTTPException(404, str(exc)) from None
    except profmod.ProfileError as exc:
        raise HTTPException(422, {"message": str(exc), "errors": field_errors(exc.problems)}) from None
    edited = path.parent == profmod.profiles_dir(data_dir)
    return {
        "name": name,
        "source": "edited" if edited else "default",
        "has_default": _has_default(name),
        "path": str(path),
        "profile": profile,
    }


@router.put("/api/profiles/{name}", dependencies=[requires(Perm.EDUCATOR)])
async def profile_save(name: str, request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    """Validate and save an edited profile to <data>/profiles/<name>.json (overrides the default of
    the same name). 422 with every problem, each with the field it is about."""
    _check_name(name)
    try:
        body = await request.json()
    except ValueError as exc:
        raise HTTPException(
            422, {"message": f"not valid JSON: {exc}", "errors": [{"field": "", "message": f"not valid JSON: {exc}"}]}
        ) from None
    if isinstance(body, dict) and "profile" in body and isinstance(body["profile"], dict) and "channels" not in body:
        body = body["profile"]  # {"profile": {...}} as well as the bare profile
    problems: list[profmod.FieldError] = []
    if isinstance(body, dict) and body.get("name") != name:
        problems.append(
            profmod.FieldError(
                "name",
                f"name {body.get('name')!r} must be {name!r} (the profile being "
                "edited); to keep both, save it under a new name",
            )
        )
    try:
        profmod.validate_profile(body)
    except profmod.ProfileError as exc:
        problems = exc.problems + problems
    if problems:
        raise HTTPException(422, {"message": "; ".join(p.message for p in problems), "errors": field_errors(problems)})
    path = await asyncio.to_thread(profmod.save_profile, body, _data_dir(request))
    audit.record(user, "profile.save", {"profile": name}, client_address(request))
    return {"name": name, "source": "edited", "has_default": _has_default(name), "path": str(path), "profile": body}


@router.delete("/api/profiles/{name}", dependencies=[requires(Perm.EDUCATOR)])
async def profile_reset(name: str, request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    """Remove the edited copy: the default of the same name applies again (404 when there was no
    edited copy). Returns what applies now (`profile` null when the name has no default)."""
    _check_name(name)
    data_dir = _data_dir(request)
    if not profmod.delete_profile(name, data_dir):
        raise HTTPException(404, f"{name!r} has no edited copy to remove")
    audit.record(user, "profile.reset", {"profile": name}, client_address(request))
    profile = profmod.load_profile(name, data_dir) if _has_default(name) else None
    return {
        "name": name,
        "source": "default" if profile else "",
        "has_default": profile is not None,
        "profile": profile,
    }
