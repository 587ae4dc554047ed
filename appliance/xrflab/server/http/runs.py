"""HTTP routes and the WebSocket endpoint. The pydantic models here are the API's contract
(they are what /openapi.json publishes); the dashboard and the CLI use nothing else.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import struct
from typing import Any, Literal

from fastapi import APIRouter, Depends, Query, Request, WebSocket
from pydantic import BaseModel, Field
from starlette.websockets import WebSocketDisconnect, WebSocketState

from ... import channels as chmod
from ... import plants
from ...errors import Denied, Invalid, Unavailable, XrfError
from ...plant_field import PlantInfo, PlantName
from ...projects.service import projects_of
from ...statemachine import StateMachine, state_machine
from ..runs import start as run_start
from ..runs.store import RunRecord  # the run record's API model, made from runs.RunRow
from ..runs.supervisor import Supervisor, SupervisorError
from ..security import audit, ownership
from ..security.auth import SAFE_COMMANDS, Perm, User, check, client_address, current_user, may, requires
from ..security.roles import role_has
from ..ws import messages
from ..ws.hub import Client

router = APIRouter(prefix="/api")


# ---- models -------------------------------------------------------------------------------------


class BenchInfo(BaseModel):
    mode: Literal["sim", "real"]
    sim: str = Field(description="simulated plant when mode is sim")
    profile: str
    evl: bool
    spidev: bool
    telemetry_hz: float = Field(description="telemetry samples a second to a dashboard")
    telemetry_per_message: int = Field(description="samples in one telemetry message (oldest first)")


class BuildInfo(BaseModel):
    name: str
    kind: Literal["example", "template", "project"]
    path: str
    sim: str = Field(description="plant a run of this build simulates by default")
    status: Literal["not built", "building", "ready", "failed"]
    error: str = ""
    label: str = Field(default="", description="project builds: '<project name> #<build id>'")
    project_id: int | None = Field(
        default=None,
        description="project builds: start them with POST /api/projects/{project_id}/builds/{build_id}/run",
    )
    build_id: int | None = None


class StartRun(BaseModel):
    build: str = Field(description="a name from GET /api/builds")
    sim: PlantName | None = Field(default=None, description="override the build's plant (GET /api/plants)")
    max_cycles: int | None = Field(default=None, ge=1, description="leave the loop after N cycles")
    log_timing: bool = Field(
        default=False,
        description="also log every cycle's framework timing (wake-up "
        "jitter, stage durations, misses) into cycle_timing.xrf, a log of the run",
    )


class ApplianceStatus(BaseModel):
    clients: int = Field(description="WebSocket clients connected")
    published: int = Field(description="messages fanned out since start")
    run_active: bool
    run_id: int | None


class CommandRequest(BaseModel):
    cmd: str | int


class CommandReply(BaseModel):
    ticket: int
    accepted: bool
    state: int
    state_name: str
    reason: str


def _supervisor(request: Request) -> Supervisor:
    return request.app.state.supervisor


# ---- REST ---------------------------------------------------------------------------------------


@router.get("/bench", response_model=BenchInfo, dependencies=[requires(Perm.WATCH)])
async def get_bench(request: Request) -> dict[str, Any]:
    return _supervisor(request).bench()


@router.get("/plants", response_model=list[PlantInfo], dependencies=[requires(Perm.WATCH)])
async def get_plants() -> list[dict[str, Any]]:
    """The simulated plants, read out of rt_core's plant table (xrflab.plants): the dashboard's
    plant menu lists these; it has no list of its own."""
    return [p.as_dict() for p in plants.plants()]


@router.get("/status", response_model=ApplianceStatus, dependencies=[requires(Perm.WATCH)])
async def get_status(request: Request) -> dict[str, Any]:
    sup = _supervisor(request)
    run = sup.current
    return {
        "clients": sup.hub.clients,
        "published": sup.hub.published,
        "run_active": bool(run and run.alive),
        "run_id": run.row.id if run else None,
    }


@router.get("/state-machine", response_model=StateMachine, dependencies=[requires(Perm.WATCH)])
async def get_state_machine() -> StateMachine:
    """FullStateMachine as the loop runs it: read out of rt_core's C command table
    (statemachine.py). The dashboard draws this; it has no copy of the transitions."""
    return state_machine()


@router.get("/ws-schema", dependencies=[requires(Perm.WATCH)])
async def get_ws_schema() -> dict[str, Any]:
    """JSON Schema of every WebSocket message of /ws, both directions (server/ws/messages.py): what
    /openapi.json is for the HTTP routes."""
    return messages.ws_schema()


@router.get("/builds", response_model=list[BuildInfo], dependencies=[requires(Perm.WATCH)])
async def get_builds(request: Request) -> list[dict[str, Any]]:
    """The bundled examples and templates, then the newest successful build of each of the
    requester's own projects (the Bench page offered only the examples, so "Start run" there
    started an example after a student had run their own project: issue 19)."""
    out = [
        {"name": e.name, "kind": e.kind, "path": str(e.path), "sim": e.sim, "status": e.status, "error": e.error}
        for e in _supervisor(request).catalog.entries()
    ]
    return out + await _own_project_builds(request)


async def _own_project_builds(request: Request) -> list[dict[str, Any]]:
    from pathlib import Path

    user = ownership.user_of(request)
    if user is None or not role_has(user.role, Perm.PROJECTS):  # observers have no projects
        return []
    svc = projects_of(request)

    def newest() -> list[dict[str, Any]]:
        found = []
        for p in svc.store.projects(owner=user.username):
            b = next(
                (
                    b
                    for b in svc.store.builds(p.id, limit=20)
                    if b.status == "ok" and b.executable and Path(b.executable).exists()
                ),
                None,
            )
            if b is not None:
                found.append(
                    {
                        "name": f"project-{p.id}-build-{b.id}",
                        "kind": "project",
                        "path": "",
                        "sim": svc.settings.sim,
                        "status": "ready",
                        "error": "",
                        "label": f"{p.name} #{b.id}",
                        "project_id": p.id,
                        "build_id": b.id,
                    }
                )
        return found

    return await asyncio.to_thread(newest)


@router.post("/runs", response_model=RunRecord, status_code=201, dependencies=[requires(Perm.DRIVE)])
async def start_run(body: StartRun, request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    try:
        # Only a bundled example/template or a build of one's own project (else: a missing build).
        await ownership.check_startable(request, body.build)
    except XrfError as exc:  # audited, then answered as it is (server/http/errors.py)
        audit.record(user, "run.start_failed", {"build": body.build, "error": str(exc)}, client_address(request))
        raise
    # The one start-a-run service (server/runs/start.py): lease bookkeeping and audit as every route;
    # a refusal is a SupervisorError (an XrfError: its status and message are the answer).
    row = await run_start.start_run(
        request, user, run_start.RunRequest(body.build, body.sim, body.max_cycles, body.log_timing)
    )
    return row.as_dict()


@router.post("/runs/current/stop", response_model=RunRecord, dependencies=[requires(Perm.DRIVE)])
async def stop_run(request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    row = await _supervisor(request).stop_current(by=user.username)  # none active: SupervisorError 409
    audit.record(user, "run.stop", {"run": row.id}, client_address(request))
    return row.as_dict()


def command_name(cmd: str | int) -> str:
    """The command's name (for the STOP rule and the audit); ValueError for unknown names. An
    unknown number stays a number (never a safe command; the loop rejects it)."""
    number = chmod.command_number(cmd)
    return next((name for name, n in chmod.COMMAND_NUMBERS.items() if n == number), str(number))


# Declared STOP: stop and pause are the safety exception anyone but an observer may send; every
# other command needs DRIVE, checked in the handler once the body names the command.
@router.post("/runs/current/command", response_model=CommandReply, dependencies=[requires(Perm.STOP)])
async def command(body: CommandRequest, request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    try:
        name = command_name(body.cmd)
    except ValueError as exc:  # an unknown command name: the request's own content
        raise Invalid(str(exc)) from None
    if name not in SAFE_COMMANDS:
        check(request, Perm.DRIVE)
    try:
        result = await _supervisor(request).command(body.cmd)  # no run / stopping: SupervisorError 409
    except ValueError as exc:  # a command number the channels cannot carry
        raise Invalid(str(exc)) from None
    except chmod.ChannelsError as exc:  # the loop's shared memory is gone or full
        raise Unavailable(str(exc)) from None
    audit.record(user, "command", {"cmd": name, "accepted": result.accepted, "via": "http"}, client_address(request))
    _zero_setpoints_after_reset(_supervisor(request), name, result.accepted)
    _tell_holder(request.app.state.security, user, name, result.accepted)
    return {
        "ticket": result.ticket,
        "accepted": result.accepted,
        "state": result.state,
        "state_name": result.state_name,
        "reason": result.reason,
    }


def _tell_holder(security: Any, user: User, name: str, accepted: bool) -> None:
    """A pause or stop by someone who does not hold the bench (the STOP rule allows it): the
    holder hears who (security/lease.py, event `intervention`)."""
    if accepted and name in SAFE_COMMANDS and security.lease is not None:
        security.lease.intervened(user, name)


def _zero_setpoints_after_reset(sup: Supervisor, name: str, accepted: bool) -> None:
    """An accepted reset starts the controller over, so its setpoints start over too (zero,
    false): with the old ones kept, the robot jumped straight back to them at the next start
    (issue 19). Every dashboard shows zeros after a reset (app.js)."""
    if name != "reset" or not accepted:
        return
    run = sup.current
    if run is None or not run.setpoint:
        return
    zeros = {  # a bounded string (header.frame_id) starts over empty: 0 would not encode
        k: (
            False if isinstance(v, bool) else [0 for _ in v] if isinstance(v, list) else "" if isinstance(v, str) else 0
        )
        for k, v in run.setpoint.items()
    }
    with contextlib.suppress(SupervisorError, ValueError, chmod.ChannelsError):
        sup.setpoint(zeros)


@router.get("/runs", response_model=list[RunRecord], dependencies=[requires(Perm.WATCH)])  # type: ignore[valid-type]
async def list_runs(request: Request, limit: int = Query(100, ge=1, le=10_000)) -> list[dict[str, Any]]:
    """Runs the user may see: all for educators, their own for students and observers."""
    return [r.as_dict() for r in ownership.runs(request, limit)]


@router.get("/runs/{run_id}", response_model=RunRecord, dependencies=[requires(Perm.WATCH)])
async def get_run(run_id: int, request: Request) -> dict[str, Any]:
    return ownership.run_or_404(request, run_id).as_dict()  # someone else's: as if it did not exist


# ---- WebSocket ----------------------------------------------------------------------------------

ws_router = APIRouter()


# Every client->server message type and the permission it needs, as its model in
# server/ws/messages.py declares it (`perm`): a type without a model is refused as unknown before
# anything else happens. `command` is STOP (stop and pause, the commands channels.h marks safe, are
# the safety exception); any other command needs DRIVE.
WS_PERMS: dict[str, Perm] = {kind: Perm(model.perm) for kind, model in messages.CLIENT_KINDS.items()}


class WsDenied(Denied):
    """The message is refused for want of a permission (error reply, `denied`); `close` when the
    session itself is gone."""

    def __init__(self, message: str, close: bool = False) -> None:
        super().__init__(message)
        self.close = close


def _ws_authorize(ws: WebSocket, client: Client, perm: Perm) -> User:
    """Re-checks the session on every message: a logout, expiry, disabled account or lost lease
    takes effect at once, not at the next connection."""
    security = ws.app.state.security
    ws.scope.pop("xrf_auth", None)
    user, _, _ = security.resolve(ws)
    if user is None:
        raise WsDenied("your session ended; log in again", close=True)
    client.user = user
    if user.must_change:
        raise WsDenied("change your password first")
    if not may(user, perm, security.lease):
        if perm is Perm.DRIVE and role_has(user.role, perm):  # the role drives, but not without the lease
            holder = security.lease.holder if security.lease else None
            who = f"{holder.user.username} holds it" if holder else "nobody holds it; take it first"
            raise WsDenied(f"you do not hold the bench ({who})")
        raise WsDenied(f"{user.role}s may not do this (needs {perm.value})")
    if perm is Perm.DRIVE and security.lease is not None:
        security.lease.touch(user)
    return user


@ws_router.websocket("/ws", dependencies=[requires(Perm.WATCH)])
async def websocket(ws: WebSocket) -> None:
    sup: Supervisor = ws.app.state.supervisor
    await ws.accept()
    # The user first: the snapshot (current run, state...) is filtered like every message.
    client = sup.hub.new_client(ws, ws.app.state.security.resolve(ws)[0])
    pump = asyncio.create_task(client.pump())
    receive = asyncio.create_task(_receive(ws, client, sup))
    kicked = asyncio.create_task(client.kicked.wait())
    try:
        await asyncio.wait({pump, receive, kicked}, return_when=asyncio.FIRST_COMPLETED)
    finally:
        sup.hub.remove(client)
        client.stop()
        for task in (pump, receive, kicked):
            task.cancel()
        if client.kicked.is_set() and ws.client_state == WebSocketState.CONNECTED:
            # 1008 policy violation: the client could not keep up (or its session ended).
            # Bounded: its socket may be full.
            reason = "session ended" if client.kick_reason.startswith("your session") else "too slow"
            with contextlib.suppress(Exception):
                await asyncio.wait_for(ws.close(code=1008, reason=reason), 1.0)


async def _receive(ws: WebSocket, client: Client, sup: Supervisor) -> None:
    limit = sup.settings.max_frame_bytes
    while True:
        try:
            message = await ws.receive()
        except (WebSocketDisconnect, RuntimeError):
            return
        if message["type"] == "websocket.disconnect":
            return
        text = message.get("text")
        if text is None:
            client.reply(messages.ErrorMessage(error="binary frames are not accepted; send JSON text"))
            continue
        if len(text) > limit:
            client.reply(messages.ErrorMessage(error=f"frame of {len(text)} bytes is over the {limit} byte limit"))
            continue
        await _handle(text, client, sup)


async def _handle(text: str, client: Client, sup: Supervisor) -> None:
    """One client message. Every failure becomes an `error` reply; nothing here can end the
    connection or reach the loop with bad data."""
    try:
        msg = json.loads(text)
    except ValueError as exc:
        client.reply(messages.ErrorMessage(error=f"malformed JSON: {exc}"))
        return
    if not isinstance(msg, dict) or not isinstance(msg.get("type"), str):
        client.reply(messages.ErrorMessage(error="a message is a JSON object with a string 'type'"))
        return
    kind = msg["type"]
    ref = msg.get("id")  # echoed so a client can match replies to requests
    perm = WS_PERMS.get(kind)
    if perm is None:
        client.reply(
            messages.ErrorMessage(
                id=ref, request=kind, error=f"unknown message type {kind!r}; types: {', '.join(WS_PERMS)}"
            )
        )
        return
    try:
        user = _ws_authorize(client.ws, client, perm)
        # The kind's model (server/ws/messages.py) checks the shape; what depends on the run (a command's
        # name, a setpoint's fields) is checked below, by what uses it.
        incoming = messages.parse_incoming(kind, msg)
        if isinstance(incoming, messages.CommandRequest):
            cmd = incoming.cmd
            name = command_name(cmd)
            if name not in SAFE_COMMANDS:
                user = _ws_authorize(client.ws, client, Perm.DRIVE)
            result = await sup.command(cmd)
            audit.record(
                user, "command", {"cmd": name, "accepted": result.accepted, "via": "ws"}, client_address(client.ws)
            )
            _zero_setpoints_after_reset(sup, name, result.accepted)
            _tell_holder(client.ws.app.state.security, user, name, result.accepted)
            client.reply(
                messages.AckMessage(
                    id=ref,
                    cmd=cmd,
                    ticket=result.ticket,
                    accepted=result.accepted,
                    state=result.state,
                    name=result.state_name,
                    reason=result.reason,
                )
            )
        elif isinstance(incoming, messages.SetpointRequest):
            merged = sup.setpoint(dict(incoming.fields))
            client.reply(messages.AckMessage(id=ref, setpoint=merged))
        elif isinstance(incoming, messages.SubscribeRequest):
            client.topics = set(incoming.topics)
            client.reply(messages.AckMessage(id=ref, topics=sorted(client.topics)))
        elif isinstance(incoming, messages.PingRequest):
            client.reply(messages.PongMessage(id=ref, t=incoming.t))
        else:
            raise ValueError(f"unknown message type {kind!r}; types: {', '.join(WS_PERMS)}")
    except XrfError as exc:
        # A service's refusal, answered as HTTP answers it (server/http/errors.py): its message; a
        # refusal for want of a permission (403: the session, the role, the lease) is flagged `denied`.
        denied = True if exc.status == 403 else None
        client.reply(messages.ErrorMessage(id=ref, request=kind, error=str(exc), denied=denied))
        if isinstance(exc, WsDenied) and exc.close:
            client.kick_reason = str(exc)
            client.kicked.set()
    except (ValueError, OverflowError, TypeError, struct.error, chmod.ChannelsError) as exc:
        client.reply(messages.ErrorMessage(id=ref, request=kind, error=str(exc)))
