"""`xrf room`: the room service. One page with every bench, the class list, the educator's actions.

A FastAPI app like the appliance, with the appliance's own login rules: the same accounts code,
sessions, CSRF, rate limits and permission declarations (``server/auth.py``,
``server/routes_accounts.py``: login, users, class-list import, password resets). The room's own
routes are for educators only, but ``POST /api/room/enrol`` (a bench's `xrf room join`, which
has no account: the one-time code is its credential).

Assignments (assignments.py) are published from here and their runs collected back as one
archive (collect.py); benches fetch and upload over HTTP with tokens signed by their own
enrolment key (``_bench_token``), never with an account.

``RoomState`` is the grid's model, fed by one MQTT subscription to ``xrf/bench/+/+`` (paho's
thread hands every message to the event loop). A bench is offline when its last will says so or
when nothing was heard from it for ``SILENT_S`` (it publishes every second): whichever comes first.
Every change is pushed to the page's WebSocket (``/api/room/ws``) at once.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import re
import secrets
import shutil
import time
from collections import deque
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fastapi import APIRouter, Depends, FastAPI, HTTPException, Query, Request, WebSocket
from fastapi.responses import FileResponse, RedirectResponse, Response
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, Field
from starlette.websockets import WebSocketDisconnect

from ..projects import archive as archive_mod
from ..projects.assignments import LIMITS as ASSIGNMENT_LIMITS
from ..server.accounts import RateLimiter
from ..server.auth import Perm, Security, SecurityHeaders, User, client_address, current_user, optional_user, requires
from ..server.body_limit import BodyLimit, spool_to_file
from ..server.settings import Settings
from . import mqtt, sso, topics
from .accounts_sync import RoomAccounts
from .assignments import RoomAssignments
from .broker import ROOM_USER, BrokerFiles, BrokerProcess
from .collect import BENCH_MAX, FORMATS, Collection, assemble
from .enrol import JoinCodes

log = logging.getLogger(__name__)

SILENT_S = 4.0  # no status for this long = offline (statuses come every second)
TICK_S = 0.25
ACCOUNTS_POLL_S = 0.5


@dataclass
class RoomConfig:
    data_dir: Path
    host: str = "127.0.0.1"
    port: int = 8100
    # what benches call the broker (its certificate names all of them), and its ports
    broker_names: list[str] = field(default_factory=lambda: ["127.0.0.1", "localhost"])
    broker_port: int | None = 1883
    broker_tls_port: int | None = 8883
    broker_bind: str = "0.0.0.0"
    tls: bool = True  # benches are enrolled to the TLS listener when there is one
    spawn_broker: bool = True  # False: mosquitto is started by someone else with <data>/broker/mosquitto.conf

    @property
    def broker_folder(self) -> Path:
        return self.data_dir / "broker"


@dataclass
class Bench:
    name: str
    status: dict[str, Any] = field(default_factory=dict)
    order: tuple[int, int] | None = None  # (boot, seq) of `status`
    online_flag: bool = False
    conn: tuple[int, int] | None = None
    heard: float = 0.0  # monotonic time of the last message
    events: deque[dict[str, Any]] = field(default_factory=lambda: deque(maxlen=50))
    event_keys: set[tuple[int, int]] = field(default_factory=set)

    @property
    def online(self) -> bool:
        return self.online_flag and time.monotonic() - self.heard < SILENT_S

    def view(self) -> dict[str, Any]:
        s = self.status
        return {
            "name": self.name,
            "online": self.online,
            "state": s.get("state", "?"),
            "holder": s.get("holder", ""),
            "run_owner": s.get("run_owner", ""),
            "run_id": s.get("run_id"),
            "alarms": s.get("alarms", []),
            "cycles": s.get("cycles"),
            "misses": s.get("misses"),
            "cycle_rate": s.get("cycle_rate"),
            "selfcheck": s.get("selfcheck"),
            "cpu_temp_c": s.get("cpu_temp_c"),
            "throttled": s.get("throttled"),
            "disk_free_mb": s.get("disk_free_mb"),
            "url": s.get("url", ""),
            "seq": s.get("seq"),
            "t": s.get("t"),
            "events_dropped": s.get("events_dropped", 0),
            "accounts_version": s.get("accounts_version", 0),
            "assignments": s.get("assignments", []),
            "events": list(self.events)[-5:],
        }


class RoomState:
    """Benches as the room knows them; `changed` names benches to push to the pages."""

    def __init__(self) -> None:
        self.benches: dict[str, Bench] = {}
        self.replies: dict[str, list[dict[str, Any]]] = {}
        self.listeners: set[asyncio.Queue[str]] = set()
        self.connected = False
        self._was_online: dict[str, bool] = {}
        self.on_reply: Any = None  # the Room's: a bench's answer to a collection

    def bench(self, name: str) -> Bench:
        b = self.benches.get(name)
        if b is None:
            b = self.benches[name] = Bench(name)
        return b

    def on_message(self, topic: str, payload: bytes | bytearray) -> None:
        parsed = topics.parse_bench_topic(topic)
        if parsed is None:
            return
        name, leaf = parsed
        try:
            body = json.loads(payload)
        except ValueError:
            return
        if not isinstance(body, dict):
            return
        b = self.bench(name)
        if leaf == "online":
            conn = tuple(body.get("conn") or (0, 0))
            if b.conn is not None and conn < b.conn:
                return  # the will of an older connection: the bench is back already
            b.conn = conn
            b.online_flag = bool(body.get("online"))
            b.heard = time.monotonic()
        elif leaf == "status":
            order = (int(body.get("boot", 0)), int(body.get("seq", 0)))
            if not topics.newer(b.order, order):
                return  # stale: a newer state is already shown
            b.order, b.status = order, body
            b.heard = time.monotonic()
        elif leaf == "event":
            key = (int(body.get("boot", 0)), int(body.get("seq", 0)))
            if key in b.event_keys:
                return  # resent after an outage, seen already
            b.event_keys.add(key)
            b.events.append(body)
        elif leaf == "reply":
            self.replies.setdefault(str(body.get("id", "")), []).append({**body, "bench": name, "t_room": time.time()})
            if self.on_reply is not None:
                self.on_reply(name, body)
            return
        self.push(name)

    def push(self, name: str) -> None:
        b = self.benches[name]
        self._was_online[name] = b.online
        text = json.dumps({"type": "bench", "bench": b.view()}, default=str)
        for q in list(self.listeners):
            if q.qsize() < 1000:
                q.put_nowait(text)

    def tick(self) -> None:
        """Benches that went silent are offline now."""
        for name, b in self.benches.items():
            if self._was_online.get(name) != b.online:
                self.push(name)

    def views(self) -> list[dict[str, Any]]:
        return [b.view() for b in self.benches.values()]


class Room:
    """Everything the routes use, on app.state.room."""

    def __init__(self, config: RoomConfig, security: Security) -> None:
        self.config = config
        self.security = security
        self.state = RoomState()
        self.codes = JoinCodes()
        self.files = BrokerFiles(
            config.broker_folder,
            port=config.broker_port,
            tls_port=config.broker_tls_port,
            bind=config.broker_bind,
            names=config.broker_names,
        )
        self.broker: BrokerProcess | None = None
        self.benches_path = config.data_dir / "benches.json"
        self.enrolled: dict[str, dict[str, Any]] = self._load_benches()
        self.enrol_limit = RateLimiter(10, 60.0, 60.0)
        self.client: Any = None
        self.loop: asyncio.AbstractEventLoop | None = None
        self.accounts: RoomAccounts | None = None
        self.assignments = RoomAssignments(config.data_dir / "assignments")
        self.collections: dict[str, Collection] = {}
        self.state.on_reply = self._on_reply
        self._verifiers: dict[tuple[str, str], sso.Verifier] = {}
        self._tasks: list[asyncio.Task[Any]] = []

    def _load_benches(self) -> dict[str, dict[str, Any]]:
        try:
            return json.loads(self.benches_path.read_text())
        except (OSError, ValueError):
            return {}

    def _save_benches(self) -> None:
        import os

        tmp = self.benches_path.with_suffix(".tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)  # SSO keys: private
        with os.fdopen(fd, "w") as f:
            json.dump(self.enrolled, f)
        tmp.replace(self.benches_path)

    # -- life -----------------------------------------------------------------------------------
    async def start(self) -> None:
        self.loop = asyncio.get_running_loop()
        self.config.data_dir.mkdir(parents=True, exist_ok=True)
        self.files.write()
        for name in self.enrolled:
            self.state.bench(name)
        if self.config.spawn_broker:
            self.broker = BrokerProcess(self.files)
            await self.loop.run_in_executor(None, self.broker.start)
            self._tasks.append(self.loop.create_task(self._watch_broker(), name="room-broker"))
        self.accounts = RoomAccounts(self.security.accounts)
        port = self.config.broker_port if self.config.broker_port is not None else self.config.broker_tls_port
        tls = self.config.broker_port is None
        endpoint = mqtt.Endpoint(
            "127.0.0.1",
            int(port or 0),
            ROOM_USER,
            self.files.room_password(),
            self.files.ca_cert.read_text() if tls else "",
        )
        c = mqtt.client(endpoint, f"room-{secrets.token_hex(4)}")
        c.on_connect = self._on_connect
        c.on_disconnect = self._on_disconnect
        c.on_message = self._on_mqtt_message
        self.client = c
        mqtt.connect_async(c, endpoint)
        c.loop_start()
        self._tasks.append(self.loop.create_task(self._ticker(), name="room-tick"))
        self._tasks.append(self.loop.create_task(self._publish_accounts(), name="room-accounts"))

    async def stop(self) -> None:
        for t in self._tasks:
            t.cancel()
        if self.client is not None:
            self.client.disconnect()
            self.client.loop_stop()
        if self.broker is not None:
            await asyncio.get_running_loop().run_in_executor(None, self.broker.stop)

    def _on_mqtt_message(self, _client: Any, _userdata: Any, msg: Any) -> None:
        # paho's network thread: the state is the event loop's, so the message is handed over.
        assert self.loop is not None, "the client starts in start(), after the loop is known"
        self.loop.call_soon_threadsafe(self.state.on_message, msg.topic, msg.payload)

    def _on_connect(self, client: Any, _u: Any, _f: Any, reason: Any, _p: Any = None) -> None:
        if not mqtt.reason_ok(reason):
            log.error("room: the broker refused the room: %s", reason)
            return
        client.subscribe(topics.BENCH_ALL, qos=1)
        self.state.connected = True
        if self.accounts is not None and self.loop is not None:
            # a restarted broker lost the retained class list and assignments: publish them again
            self.loop.call_soon_threadsafe(self._republish_accounts)
            self.loop.call_soon_threadsafe(self._republish_assignments)

    def _on_disconnect(self, *_a: Any) -> None:
        self.state.connected = False

    async def _watch_broker(self) -> None:
        """The broker the room started is started again if it dies (benches reconnect by themselves)."""
        while True:
            await asyncio.sleep(1.0)
            if self.broker is not None and self.broker.proc is not None and self.broker.proc.poll() is not None:
                log.warning("room: mosquitto exited (%s); starting it again", self.broker.proc.returncode)
                with contextlib.suppress(Exception):
                    await asyncio.get_running_loop().run_in_executor(None, self.broker.start)

    async def _ticker(self) -> None:
        while True:
            await asyncio.sleep(TICK_S)
            self.state.tick()

    def _republish_accounts(self) -> None:
        if self.accounts is not None:
            self._send_accounts(self.accounts.current())

    def _send_accounts(self, body: dict[str, Any]) -> None:
        if self.client is not None:
            self.client.publish(topics.ACCOUNTS, json.dumps(body), qos=1, retain=True)

    async def _publish_accounts(self) -> None:
        while True:
            await asyncio.sleep(ACCOUNTS_POLL_S)
            if self.accounts is not None and self.state.connected:
                body = self.accounts.changed()
                if body is not None:
                    self._send_accounts(body)

    # -- assignments and collections ------------------------------------------------------------
    def _republish_assignments(self) -> None:
        for a in self.assignments.list():
            self.publish_assignment(a["id"])

    def publish_assignment(self, aid: str) -> None:
        if self.client is not None:
            self.client.publish(topics.assignment(aid), json.dumps(self.assignments.message(aid)), qos=1, retain=True)

    def bench_token(self, bench: str, token: str, use: str, subject: str) -> None:
        """A bench's own signed token (sso.mint with its enrolment key) for `use` and `subject`; 403
        for anything else, without saying what."""
        enrolled = self.enrolled.get(bench)
        if enrolled is None:
            raise HTTPException(403, "invalid token")
        v = self._verifiers.get((bench, use))
        if v is None or v.key != enrolled["sso_key"]:
            v = self._verifiers[(bench, use)] = sso.Verifier(enrolled["sso_key"], bench, use)
        try:
            if v.verify(token) != subject:
                raise HTTPException(403, "invalid token")
        except sso.SsoError:
            raise HTTPException(403, "invalid token") from None

    def collect(self, aid: str, formats: list[str], wait_s: float, by: str) -> Collection:
        meta = self.assignments.index.get(aid)
        if meta is None:
            raise HTTPException(404, f"no assignment {aid}")
        if self.client is None or not self.state.connected:
            raise HTTPException(503, "the room is not connected to its broker")
        cid = secrets.token_hex(8)
        folder = self.config.data_dir / "collections" / cid
        folder.mkdir(parents=True, mode=0o700)
        c = Collection(cid, meta, formats, by, folder, time.time() + wait_s)
        for name in sorted(self.enrolled):  # every enrolled bench is in the manifest, answering or not
            b = self.state.benches.get(name)
            c.benches[name] = "waiting" if b is not None and b.online else "missing"
        self.collections[cid] = c
        while len(self.collections) > 20:  # the oldest collections' files go
            old = self.collections.pop(next(iter(self.collections)))
            shutil.rmtree(old.folder, ignore_errors=True)
        body = {
            "id": cid,
            "cmd": "collect",
            "by": by,
            "t": time.time(),
            "collection": cid,
            "assignment": aid,
            "formats": formats,
        }
        for name, status in c.benches.items():
            if status == "waiting":
                self.client.publish(topics.cmd(name), json.dumps(body), qos=1)
        return c

    def _on_reply(self, bench: str, body: dict[str, Any]) -> None:
        c = self.collections.get(str(body.get("id", "")))
        if c is not None and body.get("cmd") == "collect" and not body.get("ok") and c.benches.get(bench) == "waiting":
            c.benches[bench] = "failed"
            c.errors[bench] = str(body.get("error", ""))[:300]

    # -- actions --------------------------------------------------------------------------------
    def command(self, bench: str | None, cmd: str, by: str, **fields: Any) -> dict[str, Any]:
        if bench is not None and bench not in self.state.benches:
            raise HTTPException(404, f"no bench {bench}")
        cid = secrets.token_hex(8)
        t = time.time()
        body = {"id": cid, "cmd": cmd, "by": by, "t": t, **fields}
        if self.client is None or not self.state.connected:
            raise HTTPException(503, "the room is not connected to its broker")
        self.client.publish(topics.cmd(bench) if bench else topics.CMD_ALL, json.dumps(body), qos=1)
        self.state.replies[cid] = []
        if len(self.state.replies) > 500:
            self.state.replies.pop(next(iter(self.state.replies)))
        return {"id": cid, "t": t, "benches": [bench] if bench else sorted(self.state.benches)}

    def enrol(self, name: str, address: str) -> dict[str, Any]:
        name = topics.check_bench_name(name)
        password = secrets.token_urlsafe(24)
        self.files.set_password(name, password)
        self.files.reload()
        key = secrets.token_urlsafe(32)
        self.enrolled[name] = {"sso_key": key, "enrolled": time.time(), "address": address}
        self._save_benches()
        self.state.bench(name)
        tls = self.config.tls and self.config.broker_tls_port is not None
        return {
            "name": name,
            "sso_key": key,
            "broker": {
                "host": self.config.broker_names[0],
                "port": self.config.broker_tls_port if tls else self.config.broker_port,
                "username": name,
                "password": password,
                "ca_pem": self.files.ca_cert.read_text() if tls else "",
            },
        }


# ---- routes ---------------------------------------------------------------------------------------

router = APIRouter(prefix="/api/room")


def _room(request: Request | WebSocket) -> Room:
    return request.app.state.room


class EnrolRequest(BaseModel):
    code: str = Field(max_length=64)
    name: str = Field(max_length=64)


class Target(BaseModel):
    bench: str | None = Field(default=None, max_length=64, description="a bench's name; none = every bench")


class Message(Target):
    text: str = Field(min_length=1, max_length=500)


class SelfCheck(BaseModel):
    profile: str = Field(default="relbot", max_length=64)


class NewAssignment(BaseModel):
    name: str = Field(min_length=1, max_length=64)
    template: str = Field(pattern=r"^(base|20sim)$", description="one of the appliance's templates")


class Collect(BaseModel):
    formats: list[str] = Field(
        default_factory=lambda: ["csv"], max_length=3, description="conversions beside each raw log: csv, mat, parquet"
    )
    wait_s: float = Field(default=60.0, ge=1.0, le=600.0, description="how long benches have to answer")


def _clean_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.+ -]", "_", name).strip(" ._")[:64] or "assignment"


@router.get("/benches", dependencies=[requires(Perm.EDUCATOR)])
async def benches(request: Request) -> dict[str, Any]:
    room = _room(request)
    return {"connected": room.state.connected, "benches": room.state.views()}


@router.post("/join-codes", dependencies=[requires(Perm.EDUCATOR)])
async def join_code(request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    code, expires = _room(request).codes.new()
    from ..server import audit

    audit.record(user, "room.join_code", {}, client_address(request))
    return {"code": code, "expires": expires}


# PUBLIC: a bench joining has no account; the one-time code is its credential (rate-limited per address).
@router.post("/enrol", dependencies=[requires(Perm.PUBLIC)])
async def enrol(body: EnrolRequest, request: Request) -> dict[str, Any]:
    room = _room(request)
    address = client_address(request)
    if room.enrol_limit.retry_after(address) > 0:
        raise HTTPException(429, "too many wrong join codes; wait a minute")
    if not room.codes.take(body.code):
        room.enrol_limit.failed(address)
        raise HTTPException(403, "unknown or expired join code")
    try:
        return await asyncio.get_running_loop().run_in_executor(None, room.enrol, body.name, address)
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None


@router.post("/stop", dependencies=[requires(Perm.EDUCATOR)])
async def stop(body: Target, request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    return _room(request).command(body.bench, "stop", user.username)


@router.post("/message", dependencies=[requires(Perm.EDUCATOR)])
async def message(body: Message, request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    return _room(request).command(body.bench, "message", user.username, text=body.text)


@router.post("/selfcheck", dependencies=[requires(Perm.EDUCATOR)])
async def selfcheck(body: SelfCheck, request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    """Every online bench is asked; an idle one (no loop running) runs its self-check, one with a run
    going answers ``skipped: busy`` (the bench decides: the grid may be a second behind). Verdicts
    arrive in the grid (``selfcheck`` of each bench), side by side."""
    room = _room(request)
    online = sorted(b.name for b in room.state.benches.values() if b.online)
    busy = [n for n in online if room.state.benches[n].status.get("active")]
    sent = [room.command(name, "selfcheck", user.username, profile=body.profile) for name in online]
    return {"benches": online, "busy": busy, "ids": [s["id"] for s in sent]}


@router.get("/assignments", dependencies=[requires(Perm.EDUCATOR)])
async def list_assignments(request: Request) -> list[dict[str, Any]]:
    """Every published assignment and the benches that have it (their status says so)."""
    room = _room(request)
    return [
        {
            **a,
            "benches": sorted(
                b.name for b in room.state.benches.values() if a["id"] in (b.status.get("assignments") or [])
            ),
        }
        for a in room.assignments.list()
    ]


def _publish(request: Request, user: User, meta: dict[str, Any]) -> dict[str, Any]:
    from ..server import audit

    _room(request).publish_assignment(meta["id"])
    audit.record(user, "room.assignment", {"id": meta["id"], "name": meta["name"]}, client_address(request))
    return meta


@router.post("/assignments", status_code=201, dependencies=[requires(Perm.EDUCATOR)])
async def publish_template(body: NewAssignment, request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    """Publish one of the appliance's templates as an assignment called `name`."""
    room = _room(request)
    src = request.app.state.settings.projects_dir / "templates" / body.template
    meta = await asyncio.to_thread(room.assignments.add_template, _clean_name(body.name), src, user.username)
    return _publish(request, user, meta)


@router.post("/assignments/upload", status_code=201, dependencies=[requires(Perm.EDUCATOR)])
async def publish_archive(
    request: Request, name: str = Query(min_length=1, max_length=64), user: User = Depends(current_user)
) -> dict[str, Any]:
    """Publish an uploaded archive (zip, tar, tar.gz as the raw body), checked as a student's upload."""
    room = _room(request)
    room.assignments.folder.mkdir(parents=True, exist_ok=True)
    path = await spool_to_file(request, room.assignments.folder, ASSIGNMENT_LIMITS.max_upload, prefix=".upload-")
    try:
        meta = await asyncio.to_thread(room.assignments.add, _clean_name(name), path, user.username)
    except archive_mod.ArchiveRejected as exc:
        raise HTTPException(422, f"archive refused: {exc}") from None
    finally:
        path.unlink(missing_ok=True)
    return _publish(request, user, meta)


# PUBLIC: a bench has no account here; its token, signed with its own enrolment key, is the credential.
@router.get("/assignments/{aid}/archive", dependencies=[requires(Perm.PUBLIC)])
async def assignment_archive(
    aid: str, request: Request, bench: str = Query(max_length=64), token: str = Query(max_length=1000)
) -> Response:
    room = _room(request)
    room.bench_token(bench, token, "assignment", aid)
    if aid not in room.assignments.index:
        raise HTTPException(404, f"no assignment {aid}")
    return FileResponse(room.assignments.archive_path(aid), media_type="application/gzip")


@router.post("/assignments/{aid}/collect", status_code=201, dependencies=[requires(Perm.EDUCATOR)])
async def collect(aid: str, body: Collect, request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    """Ask every enrolled bench for the runs of projects made from `aid`; offline ones are missing.
    Follow ``GET /api/room/collections/<id>`` until ``done``, then download its ``archive``."""
    from ..server import audit

    bad = [f for f in body.formats if f not in FORMATS]
    if bad:
        raise HTTPException(422, f"formats: {', '.join(FORMATS)} (not {', '.join(bad)})")
    c = _room(request).collect(aid, sorted(set(body.formats)), body.wait_s, user.username)
    audit.record(user, "room.collect", {"assignment": aid, "collection": c.id}, client_address(request))
    return c.view()


def _collection(request: Request, cid: str) -> Collection:
    c = _room(request).collections.get(cid)
    if c is None:
        raise HTTPException(404, f"no collection {cid}")
    return c


@router.get("/collections/{cid}", dependencies=[requires(Perm.EDUCATOR)])
async def collection(cid: str, request: Request) -> dict[str, Any]:
    return _collection(request, cid).view()


# PUBLIC: as the archive above, the bench's signed token is the credential.
@router.post("/collections/{cid}/benches/{bench}", dependencies=[requires(Perm.PUBLIC)])
async def collection_upload(
    cid: str, bench: str, request: Request, token: str = Query(max_length=1000)
) -> dict[str, Any]:
    room = _room(request)
    room.bench_token(bench, token, "collect", cid)
    c = room.collections.get(cid)
    if c is None or c.benches.get(bench) != "waiting":
        raise HTTPException(409, "this collection does not wait for this bench (too late, or sent already)")
    path = await spool_to_file(request, c.folder, BENCH_MAX, prefix=".upload-")
    os.replace(path, c.upload_path(bench))
    c.benches[bench] = "collected"
    return {"ok": True}


@router.get("/collections/{cid}/archive", dependencies=[requires(Perm.EDUCATOR)])
async def collection_archive(cid: str, request: Request) -> Response:
    """One zip: ``<student>/<bench>/<run id>/...`` and ``manifest.json`` (benches that did not
    answer are listed as missing). 409 while benches are still expected."""
    c = _collection(request, cid)
    if not c.done:
        raise HTTPException(409, "benches are still sending; see GET /api/room/collections/" + cid)
    if c.archive is None:
        out = c.folder / "collection.zip"
        await asyncio.to_thread(assemble, c, out)
        c.archive = out
    name = re.sub(r"[^A-Za-z0-9_.-]", "_", c.assignment["name"]) or "assignment"
    return FileResponse(c.archive, media_type="application/zip", filename=f"{name}-runs-{cid[:6]}.zip")


@router.get("/commands/{cid}", dependencies=[requires(Perm.EDUCATOR)])
async def replies(cid: str, request: Request) -> dict[str, Any]:
    return {"id": cid, "replies": _room(request).state.replies.get(cid, [])}


@router.post("/benches/{name}/sso", dependencies=[requires(Perm.EDUCATOR)])
async def sign_on(name: str, request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    room = _room(request)
    enrolled = room.enrolled.get(name)
    bench = room.state.benches.get(name)
    if enrolled is None or bench is None or not bench.status.get("url"):
        raise HTTPException(404, f"no bench {name} with a known address")
    token = sso.mint(enrolled["sso_key"], name, user.username)
    return {"url": f"{bench.status['url']}/room/sso?token={token}"}


ws_router = APIRouter()


@ws_router.websocket("/api/room/ws", dependencies=[requires(Perm.EDUCATOR)])
async def room_ws(ws: WebSocket) -> None:
    room = _room(ws)
    await ws.accept()
    q: asyncio.Queue[str] = asyncio.Queue()
    room.state.listeners.add(q)
    try:
        await ws.send_text(
            json.dumps(
                {"type": "snapshot", "connected": room.state.connected, "benches": room.state.views()}, default=str
            )
        )

        async def pump() -> None:
            while True:
                await ws.send_text(await q.get())

        async def drain() -> None:
            while True:
                m = await ws.receive()
                if m["type"] == "websocket.disconnect":
                    return

        tasks = {asyncio.create_task(pump()), asyncio.create_task(drain())}
        _, pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        for t in pending:
            t.cancel()
    except (WebSocketDisconnect, RuntimeError):
        pass
    finally:
        room.state.listeners.discard(q)


class RoomBodyLimit(BodyLimit):
    """The room's uploads (an assignment's archive, a bench's collection) stream to a file in their
    route, bounded there; every other body is small."""

    UPLOADS = re.compile(r"^/api/room/(assignments/upload|collections/[^/]+/benches/[^/]+)/?$")

    def _is_upload(self, scope: Any) -> bool:
        return scope.get("method") == "POST" and bool(self.UPLOADS.match(scope.get("path", "")))


def create_room_app(config: RoomConfig) -> FastAPI:
    settings = Settings(data_dir=config.data_dir, host=config.host, port=config.port)
    security = Security(settings)
    room = Room(config, security)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        from ..server import audit as auditmod
        from ..server.accounts import Accounts
        from ..server.audit import AuditLog
        from ..server.auth import bootstrap_admin

        config.data_dir.mkdir(parents=True, exist_ok=True)
        security.accounts = Accounts(settings.accounts_db, settings.session_max_s, settings.session_idle_s)
        security.audit = AuditLog(settings.audit_db)
        auditmod.use(security.audit)
        bootstrap_admin(security.accounts)
        await room.start()
        try:
            yield
        finally:
            await room.stop()
            security.close()

    app = FastAPI(title="XRF Lab room", lifespan=lifespan, openapi_url=None, docs_url=None, redoc_url=None)
    app.state.settings = settings
    app.state.security = security
    app.state.room = room
    app.add_middleware(SecurityHeaders)
    app.add_middleware(RoomBodyLimit, limit=settings.max_body_bytes, upload_limit=BENCH_MAX + (1 << 20))
    from ..server.routes_accounts import router as accounts_router

    app.include_router(accounts_router)
    app.include_router(router)
    app.include_router(ws_router)
    frontend = settings.frontend_dir
    app.mount("/static", StaticFiles(directory=frontend), name="static")

    @app.get("/", include_in_schema=False, dependencies=[requires(Perm.PUBLIC)])
    async def index(request: Request) -> Response:
        if optional_user(request) is None:
            return RedirectResponse("/login", status_code=303)
        return FileResponse(frontend / "room.html", headers={"Cache-Control": "no-cache"})

    return app
