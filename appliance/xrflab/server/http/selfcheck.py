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

The one check at a time is the self-check service's (xrflab/selfcheck_service.py, made in the app's
lifespan and reached through the ``selfcheck_of`` dependency); these routes only call it.
"""

from __future__ import annotations

import asyncio
import re
from pathlib import Path
from typing import Any, Literal

from fastapi import APIRouter, Depends, Request
from fastapi.responses import Response
from pydantic import BaseModel, Field

from ... import profiles as profmod
from ... import selfcheck as scmod
from ...errors import Conflict, Invalid, NotFound, XrfError
from ...selfcheck_service import StartCheck, field_errors, selfcheck_of
from ..security import audit
from ..security.auth import Perm, User, client_address, current_user, requires

router = APIRouter(tags=["self-check"])

REPORT_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,120}$")
MAX_REPORTS_LISTED = 200


# ---- models -------------------------------------------------------------------------------------


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


# ---- routes: the check --------------------------------------------------------------------------


@router.get("/api/selfcheck", dependencies=[requires(Perm.EDUCATOR)])
async def selfcheck_status(request: Request) -> dict[str, Any]:
    """What a check would use now, whether the bench is free, the check under way and the last result."""
    svc = selfcheck_of(request)
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
    active = await selfcheck_of(request).start(body, user, client_address(request))
    return active.payload()


@router.post("/api/selfcheck/abort", dependencies=[requires(Perm.EDUCATOR)])
async def selfcheck_abort(request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    """Abort the running check: the checker zeroes PWM and digital outputs and stops (the report
    says outputs_zeroed)."""
    svc = selfcheck_of(request)
    active = svc.current
    if not svc.abort():
        raise Conflict("no self-check is running")
    audit.record(user, "selfcheck.abort", {"check": active.id if active else None}, client_address(request))
    return {"aborting": active.id if active else None}


def _report_path(request: Request, name: str) -> Path:
    if not REPORT_NAME_RE.match(name) or ".." in name:
        raise NotFound("no such report")
    path = scmod.reports_dir(selfcheck_of(request).settings.data_dir) / f"{name}.json"
    if not path.is_file():
        raise NotFound("no such report")
    return path


@router.get("/api/selfcheck/reports", response_model=list[ReportSummary], dependencies=[requires(Perm.EDUCATOR)])
async def selfcheck_reports(request: Request) -> list[dict[str, Any]]:
    """Saved reports, newest first."""
    settings = selfcheck_of(request).settings

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
        raise XrfError(f"cannot read the report: {exc}", 500) from None
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
        raise XrfError(f"cannot read the report: {exc}", 500) from None
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
        raise NotFound(f"no bench profile named {name!r}")


@router.get("/api/profiles/{name}", dependencies=[requires(Perm.EDUCATOR)])
async def profile_get(name: str, request: Request) -> dict[str, Any]:
    _check_name(name)
    data_dir = _data_dir(request)
    try:
        path = profmod.find_profile(name, data_dir)
        profile = profmod.load_profile(path)
    except profmod.ProfileNotFound as exc:
        raise NotFound(str(exc)) from None
    except profmod.ProfileError as exc:
        raise Invalid(str(exc), detail={"message": str(exc), "errors": field_errors(exc.problems)}) from None
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
        raise Invalid(
            f"not valid JSON: {exc}",
            detail={
                "message": f"not valid JSON: {exc}",
                "errors": [{"field": "", "message": f"not valid JSON: {exc}"}],
            },
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
        raise Invalid(
            "; ".join(p.message for p in problems),
            detail={"message": "; ".join(p.message for p in problems), "errors": field_errors(problems)},
        )
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
        raise NotFound(f"{name!r} has no edited copy to remove")
    audit.record(user, "profile.reset", {"profile": name}, client_address(request))
    profile = profmod.load_profile(name, data_dir) if _has_default(name) else None
    return {
        "name": name,
        "source": "default" if profile else "",
        "has_default": profile is not None,
        "profile": profile,
    }
