"""HTTP routes of the 3D view (xrflab.viz): where its viser server listens, what the scene shows
now, reset odometry, replay a finished run. The scene itself is served by viser on an internal
port (127.0.0.1 only); the dashboard embeds it in an iframe at ``/viser/``, the appliance's
reverse proxy to it behind the login (server/http/viser.py)."""

from __future__ import annotations

import asyncio
from typing import Any

from fastapi import APIRouter, Request
from pydantic import BaseModel, Field

from ...errors import Conflict, NotFound, Unavailable
from ..security import ownership
from ..security.auth import Perm, requires

router = APIRouter(prefix="/api/viz", tags=["3d view"])


class VizInfo(BaseModel):
    available: bool = Field(description="false when viser could not start; `error` says why")
    started: bool = Field(description="viser is running: it starts at the first watcher, not with the appliance")
    url: str = Field(description="where browsers open the scene: the appliance's /viser/ proxy (login required)")
    port: int | None = Field(
        description="internal port of the viser server (127.0.0.1 only, not reachable from the LAN)"
    )
    error: str
    update_hz: float
    watched: bool = Field(description="someone watches (a viser client, or the state polled): the scene updates")
    frames: int = Field(description="scene updates sent so far (none while nobody watches)")
    handovers: int = Field(
        description="batches of telemetry the 3D view took from the run's reader so far (every few seconds "
        "while nobody watches, as they come while someone does)"
    )


class ReplayRequest(BaseModel):
    run_id: int


class SeekRequest(BaseModel):
    t: float = Field(description="seconds from the start of the recording")


def _viz(request: Request) -> Any:
    viz = getattr(request.app.state, "viz", None)
    if viz is None:
        raise Unavailable("the 3D view is not running")
    return viz


@router.get("", response_model=VizInfo, dependencies=[requires(Perm.WATCH)])
async def viz_info(request: Request) -> dict[str, Any]:
    return _viz(request).info()


@router.get("/state", dependencies=[requires(Perm.WATCH)])
async def viz_state(request: Request) -> dict[str, Any]:
    """What the scene shows now: mode (idle/live/replay), robot kind, joint angles (rad) or
    pose (m, rad), the setpoint ghost, and a message when there is no usable profile."""
    viz = _viz(request)
    viz.state_asked()  # keeps the scene updating while the state is polled (viz/scene.py)
    shown = dict(viz.shown)
    # The pose and the ghost are the robot's motion (everyone's); the raw Ros2Xeno setpoint
    # (the student's field names and values) only for the run's owner (server/security/ownership.py).
    if "setpoint" in shown and not ownership.current_run_is_visible(request, shown.get("run_id")):
        shown["setpoint"] = {}
    return {**viz.info(), **shown}


# The scene is one, shared by everyone watching: changing what it shows is driving (the bench
# holder, or an educator); a replay is only of a run the user may see (server/security/ownership.py).
@router.post("/reset-odometry", dependencies=[requires(Perm.DRIVE)])
async def reset_odometry(request: Request) -> dict[str, Any]:
    if not _viz(request).reset_odometry():
        raise Conflict("no RELbot is shown live: nothing to reset")
    return {"ok": True}


@router.get("/recordings", dependencies=[requires(Perm.WATCH)])
async def recordings(request: Request) -> list[dict[str, Any]]:
    user = ownership.user_of(request)
    return [r for r in _viz(request).recordings() if ownership.may_see(user, _run_owner(request, r["run_id"]))]


def _run_owner(request: Request, run_id: int) -> str | None:
    row = request.app.state.supervisor.store.get(run_id)
    return row.owner if row is not None else None


@router.post("/replay", dependencies=[requires(Perm.DRIVE)])
async def replay(body: ReplayRequest, request: Request) -> dict[str, Any]:
    viz = _viz(request)
    # Someone else's run: word for word the answer of a run without a recording (viz.load_replay)
    ownership.require(
        ownership.user_of(request),
        request.app.state.supervisor.store.get(body.run_id),
        lambda r: r.owner,
        "run",
        body.run_id,
        detail=f"run {body.run_id} has no 3D recording",
    )
    try:
        r = await asyncio.to_thread(viz.load_replay, body.run_id)
    # viz/scene.py says what went wrong with builtin errors; what each means to the caller:
    except LookupError as exc:  # no recording of that run
        raise NotFound(str(exc)) from None
    except OSError as exc:  # a recording file that is not a plain one of the run, or too large
        raise NotFound(f"run {body.run_id} has no 3D recording that can be replayed: {exc.strerror}") from None
    except ValueError as exc:  # a recording that cannot be shown now
        raise Conflict(str(exc)) from None
    return {"run_id": r.run_id, "duration": r.duration, "kind": r.kind, "samples": len(r.t), "message": r.message}


@router.post("/replay/seek", dependencies=[requires(Perm.DRIVE)])
async def seek(body: SeekRequest, request: Request) -> dict[str, Any]:
    try:
        return {"t": _viz(request).seek(body.t)}
    except LookupError as exc:  # nothing is being replayed
        raise Conflict(str(exc)) from None


@router.post("/live", dependencies=[requires(Perm.DRIVE)])
async def live(request: Request) -> dict[str, Any]:
    _viz(request).go_live()
    return {"ok": True}
