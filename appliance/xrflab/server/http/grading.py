"""HTTP routes of grading (issue 32; the service is xrflab/grading/service.py,
docs/educators/grading.md "HTTP API").

- ``PUT /api/assignments/{aid}/scenario`` (body: the TOML text): educators; a refused scenario
  is 422 with ``{"detail": {"error", "line", "file"}}``.
- ``GET /api/assignments/{aid}/scenario``: students and up (what their project is checked on).
- ``POST /api/projects/{pid}/grade``: the project's owner or an educator; queued (202); a
  student asking again within the service's interval gets 429 with Retry-After.
- ``GET /api/projects/{pid}/grade``: the latest job and result (with plots); owner or educator.
- ``GET /api/assignments/{aid}/grades``, ``POST .../grades/rerun``, ``GET .../grades.csv``: educators.
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Depends, Request
from fastapi.responses import JSONResponse, Response

from ...errors import TooLarge
from ...grading.scenario import MAX_BYTES
from ...grading.service import GradingService, grading_of
from ...projects.service import projects_of
from ..security import audit, ownership
from ..security import auth as authmod
from ..security.auth import Perm, requires

router = APIRouter(tags=["grading"])


def _user(request: Request) -> Any:
    return ownership.user_of(request)


@router.put("/api/assignments/{aid}/scenario", dependencies=[requires(Perm.EDUCATOR)])
async def put_scenario(aid: str, request: Request, svc: GradingService = Depends(grading_of)) -> dict[str, Any]:
    body = b""
    async for chunk in request.stream():
        body += chunk
        if len(body) > MAX_BYTES:
            raise TooLarge(f"a scenario is at most {MAX_BYTES >> 10} KiB")
    scenario = svc.set_scenario(aid, body.decode("utf-8", "replace"))
    audit.record(_user(request), "grading.scenario", {"assignment": aid}, authmod.client_address(request))
    return svc.summary(scenario)


@router.get("/api/assignments/{aid}/scenario", dependencies=[requires(Perm.PROJECTS)])
async def get_scenario(aid: str, svc: GradingService = Depends(grading_of)) -> dict[str, Any]:
    return svc.summary(svc.scenario(aid))


@router.post("/api/projects/{pid}/grade", status_code=202, dependencies=[requires(Perm.PROJECTS)])
async def grade_project(pid: int, request: Request, svc: GradingService = Depends(grading_of)) -> JSONResponse:
    user = _user(request)
    project = projects_of(request).project_for(user, pid)  # another's: 404, like a missing one
    svc.assignment_of(project)
    svc.scenario(svc.assignment_of(project))
    if user is not None and not authmod.may(user, Perm.EDUCATOR):
        svc.check_rate(user.username)
    job = svc.grade(project)
    return JSONResponse({"job": job.as_dict()}, status_code=202)


@router.get("/api/projects/{pid}/grade", dependencies=[requires(Perm.PROJECTS)])
async def project_grade(pid: int, request: Request, svc: GradingService = Depends(grading_of)) -> dict[str, Any]:
    project = projects_of(request).project_for(_user(request), pid)
    return svc.result(project)


@router.get("/api/assignments/{aid}/grades", dependencies=[requires(Perm.EDUCATOR)])
async def grades(aid: str, svc: GradingService = Depends(grading_of)) -> dict[str, Any]:
    return svc.table(aid)


@router.post("/api/assignments/{aid}/grades/rerun", status_code=202, dependencies=[requires(Perm.EDUCATOR)])
async def rerun(aid: str, request: Request, svc: GradingService = Depends(grading_of)) -> JSONResponse:
    progress = svc.rerun_all(aid)
    audit.record(_user(request), "grading.rerun", {"assignment": aid}, authmod.client_address(request))
    return JSONResponse({"progress": progress}, status_code=202)


@router.get("/api/assignments/{aid}/grades.csv", dependencies=[requires(Perm.EDUCATOR)])
async def grades_csv(aid: str, svc: GradingService = Depends(grading_of)) -> Response:
    return Response(
        svc.csv(aid),
        media_type="text/csv",
        headers={"Content-Disposition": f'attachment; filename="grades-{aid}.csv"'},
    )
