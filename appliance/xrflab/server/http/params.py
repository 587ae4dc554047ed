"""HTTP routes of live parameter tuning (issue 28; the service is xrflab/params/service.py).

- ``GET /api/params``: the current run's parameters (name, unit, default, range, value), or a note
  saying why there are none; every watcher.
- ``GET /api/params/{name}``: one of them.
- ``POST /api/params``: ``{"values": {name: number, ...}, "ranges": {name: [min, max]}}`` applied
  as one set at one cycle boundary; the answer names that cycle. The bench holder only
  (``Perm.DRIVE``: educators always); a refusal applies nothing.
- ``GET /api/params-file``: the current values as the project's saved-parameters file
  (``xrf_params.json``); saved as a version through the editor's API, a run of the project starts
  with them.
- ``GET /api/logs/runs/{id}/param-changes?fmt=json|csv``: the run's change table (cycle, time,
  name, old, new, who), beside its log files.
"""

from __future__ import annotations

from typing import Any, Literal

from fastapi import APIRouter, Depends, Request
from fastapi.responses import Response
from pydantic import BaseModel, Field

from ...logs.convert import changes_csv
from ...params.service import ParamsService, params_of
from ..security import ownership
from ..security.auth import Perm, User, current_user, requires

router = APIRouter(tags=["parameters"])


class ParamSet(BaseModel):
    # Any: a value's type is checked by the service, so "wrong type" reads as the others do.
    values: dict[str, Any] = Field(description="parameter name -> new value (a finite number)")
    ranges: dict[str, Any] = Field(
        default_factory=dict, description="parameter name -> [min, max]: widen a range the controller did not declare"
    )


@router.get("/api/params", dependencies=[requires(Perm.WATCH)])
async def list_params(svc: ParamsService = Depends(params_of)) -> dict[str, Any]:
    return svc.listing()


@router.get("/api/params-file", dependencies=[requires(Perm.WATCH)])
async def params_file(svc: ParamsService = Depends(params_of)) -> dict[str, Any]:
    """The current values as the project's saved-parameters file (path and text), to save as the
    project's next version with PUT /api/projects/{pid}/files/{path}?build=false."""
    return svc.saved_file()


@router.get("/api/params/{name:path}", dependencies=[requires(Perm.WATCH)])
async def get_param(name: str, svc: ParamsService = Depends(params_of)) -> dict[str, Any]:
    return svc.get(name)


@router.post("/api/params", dependencies=[requires(Perm.DRIVE)])
async def set_params(
    body: ParamSet, user: User = Depends(current_user), svc: ParamsService = Depends(params_of)
) -> dict[str, Any]:
    return await svc.set(body.values, user.username, body.ranges)


@router.get("/api/logs/runs/{run_id}/param-changes", dependencies=[requires(Perm.WATCH)], response_model=None)
async def param_changes(
    run_id: int, request: Request, fmt: Literal["json", "csv"] = "json", svc: ParamsService = Depends(params_of)
) -> Any:
    ownership.run_or_404(request, run_id)  # someone else's run answers as a missing one
    rows = svc.changes(run_id)
    if fmt == "json":
        return {"run": run_id, "changes": rows}
    headers = {"Content-Disposition": f'attachment; filename="run{run_id}_param_changes.csv"'}
    return Response(changes_csv(rows), media_type="text/csv", headers=headers)
