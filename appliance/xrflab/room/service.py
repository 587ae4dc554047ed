"""`xrf room`: the room service. One page with every bench, the class list, the educator's actions.

A FastAPI app like the appliance, with the appliance's own login rules: the same accounts code,
sessions, CSRF, rate limits and permission declarations (``server/security/auth.py``,
``server/http/accounts.py``: login, users, class-list import, password resets). The room's own
routes are for educators only, but ``POST /api/room/enrol`` (a bench's `xrf room join`, which
has no account: the one-time code is its credential).

Assignments (assignments.py) are published from here and their runs collected back as one
archive (collect.py); benches fetch and upload over HTTP with tokens signed by their own key
(``bench_token``: checked with the public key the bench gave at enrolment), never with an account.

What the room believes about a bench comes from its enrolment (``Enrolled``, in
``<room data>/benches.json``): its name, its public key and its dashboard address, recorded when
an educator's join code was used and changed only by an educator (``PATCH /api/room/benches/<name>``)
or a new enrolment. A bench's messages only fill its tile: "open bench" signs the educator on at
the enrolled address, whatever a status says.

``RoomState`` is the grid's model, fed by one MQTT subscription to ``xrf/bench/+/+`` (paho's
thread hands every message to the event loop). Only enrolled names are heard; every payload is
parsed by its model (payloads.py) and dropped (counted in the tile's ``dropped``, logged) when it
does not fit. A bench is offline when its last will says so or when nothing was heard from it for
``SILENT_S`` (it publishes every second): whichever comes first. Every change is pushed to the
page's WebSocket (``/api/room/ws``) at once.

Which status the tile shows: the newest by the bench's (boot, seq), but a bench cannot make itself
"newer" for good. A status whose boot is more than ``BOOT_AHEAD_MS`` ahead of the room's clock is
dropped; a retained status (from the past, delivered when the room subscribes) is replaced by the
first live one whatever its order; and the shown status only holds off older ones while it is live,
i.e. was received within ``STALE_S``: when the source of a "newer" status falls silent (a forged
one, or a bench whose clock went back), the live bench's next status is shown again.
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
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fastapi import APIRouter, Depends, FastAPI, Query, Request, WebSocket
from fastapi.responses import FileResponse, RedirectResponse, Response
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from starlette.websockets import WebSocketDisconnect

from .. import plants
from ..errors import Busy, Conflict, Denied, Invalid, NotFound, TooLarge, Unavailable
from ..grading.scenario import MAX_BYTES as SCENARIO_MAX_BYTES
from ..grading.scenario import Scenario
from ..grading.scenario import load as load_scenario
from ..grading.service import grades_csv as table_csv
from ..projects import archive as archive_mod
from ..projects.assignments import LIMITS as ASSIGNMENT_LIMITS
from ..server.http import errors as http_errors
from ..server.security.accounts import RateLimiter
from ..server.security.auth import (
    Perm,
    Security,
    SecurityHeaders,
    User,
    client_address,
    current_user,
    optional_user,
    requires,
)
from ..server.security.body_limit import BodyLimit, spool_to_file
from ..server.settings import Settings
from . import mqtt, payloads, sso, topics
from .accounts_sync import RoomAccounts
from .assignments import RoomAssignments
from .broker import ROOM_USER, BrokerFiles, BrokerProcess, private_write
from .collect import BENCH_MAX, FORMATS, Collection, assemble
from .enrol import REENROL, EnrolAnswer, EnrolRequest, JoinCodes, check_url
from .publisher import Recent

log = logging.getLogger(__name__)

SILENT_S = 4.0  # no status for this long = offline (statuses come every second)
STALE_S = 2.5  # the shown status holds off older ones for this long after it was received
BOOT_AHEAD_MS = 24 * 3600 * 1000  # a bench's boot (ms since the epoch) ahead of the room's clock: dropped
TICK_S = 0.25
ACCOUNTS_POLL_S = 0.5
MAX_EVENT_KEYS = 1000  # (boot, seq) of recent events, to drop duplicates
MAX_REPLIES = 500  # commands whose answers the room keeps


@dataclass
class RoomConfig:
    data_dir: Path
    host: str = "127.0.0.1"
    port: int = 8100
    # what benches call the broker (its certificate names all of them), and its ports
    broker_names: list[str] = field(default_factory=lambda: ["127.0.0.1", "localhost"])
    broker_port: int | None = topics.MQTT_PORT
    broker_tls_port: int | None = topics.MQTT_TLS_PORT
    broker_bind: str = "0.0.0.0"
    tls: bool = True  # benches are enrolled to the TLS listener when there is one
    spawn_broker: bool = True  # False: mosquitto is started by someone else with <data>/broker/mosquitto.conf

    @property
    def broker_folder(self) -> Path:
        return self.data_dir / "broker"


class Enrolled(BaseModel):
    """A bench as its enrolment recorded it (benches.json). `bench_key`: its Ed25519 public key;
    `url`: its dashboard. Both empty: enrolled before signed tokens (``outdated``)."""

    model_config = ConfigDict(extra="ignore")

    enrolled: float = 0.0
    address: str = Field(default="", max_length=100, description="where the enrolment came from")
    url: str = Field(default="", max_length=200)
    bench_key: str = Field(default="", max_length=64)

    @property
    def outdated(self) -> bool:
        return not (self.url and self.bench_key)


@dataclass
class Bench:
    name: str
    url: str = ""  # from its enrolment
    outdated: bool = False
    status: payloads.Status | None = None
    order: tuple[int, int] = (0, 0)  # (boot, seq) of `status`
    shown_at: float = -1e9  # monotonic time the shown status was received live (retained: never)
    online_flag: bool = False
    conn: tuple[int, int] | None = None
    heard: float = -1e9  # monotonic time of the last live message
    events: deque[payloads.Event] = field(default_factory=lambda: deque(maxlen=50))
    event_keys: Recent = field(default_factory=lambda: Recent(MAX_EVENT_KEYS))
    dropped: int = 0
    problem: str = ""

    @property
    def online(self) -> bool:
        return self.online_flag and time.monotonic() - self.heard < SILENT_S

    def view(self) -> dict[str, Any]:
        s = self.status if self.status is not None else payloads.Status(boot=0, seq=0)
        return {
            "name": self.name,
            "online": self.online,
            "url": self.url,
            "enrolment": "outdated" if self.outdated else "ok",
            "problem": self.problem or (f"enrolled before signed tokens: {REENROL}" if self.outdated else ""),
            "dropped": self.dropped,
            "state": s.state,
            "holder": s.holder,
            "run_owner": s.run_owner,
            "run_id": s.run_id,
            "alarms": [a.model_dump() for a in s.alarms],
            "cycles": s.cycles,
            "misses": s.misses,
            "cycle_rate": s.cycle_rate,
            "selfcheck": s.selfcheck.model_dump() if s.selfcheck is not None else None,
            "cpu_temp_c": s.cpu_temp_c,
            "throttled": s.throttled,
            "disk_free_mb": s.disk_free_mb,
            "seq": s.seq if self.status is not None else None,
            "t": s.t,
            "events_dropped": s.events_dropped,
            "accounts_version": s.accounts_version,
            "assignments": list(s.assignments),
            "active": s.active,
            "events": [e.model_dump() for e in list(self.events)[-5:]],
        }


class RoomState:
    """Benches as the room knows them; `changed` names benches to push to the pages. `enrolled`
    says which names are benches (the room's enrolments): nothing else is heard."""

    def __init__(self, enrolled: Callable[[str], bool] = lambda _name: True) -> None:
        self.benches: dict[str, Bench] = {}
        self.replies: dict[str, list[dict[str, Any]]] = {}
        self.listeners: set[asyncio.Queue[str]] = set()
        self.connected = False
        self.enrolled = enrolled
        self.drops = payloads.Drops("room")
        self._was_online: dict[str, bool] = {}
        self.on_reply: Any = None  # the Room's: a bench's answer to a collection
        # assignment -> bench -> its newest grading table (payloads.Grades); only the room's own
        # assignments are kept (`known_assignment`), and a bench's table only under its own name
        self.grades: dict[str, dict[str, payloads.Grades]] = {}
        self.known_assignment: Callable[[str], bool] = lambda _aid: True

    def bench(self, name: str) -> Bench:
        b = self.benches.get(name)
        if b is None:
            b = self.benches[name] = Bench(name)
        return b

    def on_message(self, topic: str, payload: bytes | bytearray, retained: bool = False) -> None:
        """One message from the broker (the event loop). `retained`: delivered from the broker's
        store when the room subscribed, i.e. from the past, not from a live connection."""
        parsed = topics.parse_bench_topic(topic)
        if parsed is None:
            return
        name, leaf = parsed
        if not payload:
            return  # a retained message cleared
        if not self.enrolled(name):
            self.drops.drop(name, topic, "not an enrolled bench")
            return
        adapter = payloads.BENCH_LEAVES.get(leaf)
        b = self.bench(name)
        try:
            if adapter is None:
                raise payloads.Malformed(f"no such topic {leaf!r}")
            msg = payloads.parse(adapter, payload, payloads.LEAF_MAX_BYTES.get(leaf, payloads.BENCH_MAX_BYTES))
            changed = self._apply(b, msg, retained)
        except payloads.Malformed as exc:
            b.dropped += 1
            self.drops.drop(name, topic, str(exc))
            return
        if changed:
            self.push(name)

    def _apply(self, b: Bench, msg: Any, retained: bool) -> bool:
        """A parsed message into the bench's state; whether the tile changed. Malformed: dropped."""
        now = time.monotonic()
        if isinstance(msg, payloads.Online):
            if not retained:
                b.heard = now
            if msg.online:
                b.conn, b.online_flag = msg.conn, True
            elif b.conn is None or msg.conn >= b.conn:
                b.online_flag = False  # not the will of a connection older than the live one
            return True
        if isinstance(msg, payloads.Status):
            ahead_ms = msg.boot - time.time_ns() // 1_000_000
            if ahead_ms > BOOT_AHEAD_MS:
                b.problem = (
                    f"its boot counter is {ahead_ms // 3_600_000} h ahead of the room's clock: check the "
                    "bench's clock, then remove <data>/room/boot there"
                )
                raise payloads.Malformed(f"boot {msg.boot} is {ahead_ms} ms ahead of the room's clock")
            if not retained:
                b.heard, b.online_flag = now, True  # a live status: the bench is connected now
            order = (msg.boot, msg.seq)
            live = now - b.shown_at < STALE_S
            if b.status is not None and order <= b.order and (retained or live):
                return False  # older than the shown one, which is live: a duplicate or a delayed one
            b.status, b.order, b.problem = msg, order, ""
            b.shown_at = -1e9 if retained else now
            return True
        if isinstance(msg, payloads.Reply):
            replies = self.replies.get(msg.id)
            if replies is None or any(r["bench"] == b.name for r in replies):
                raise payloads.Malformed(f"a reply to {msg.id}, which the room did not ask of it")
            replies.append({**msg.model_dump(exclude_none=True), "bench": b.name, "t_room": time.time()})
            if self.on_reply is not None:
                self.on_reply(b.name, msg)
            return False
        if isinstance(msg, payloads.Grades):
            if not self.known_assignment(msg.assignment):
                raise payloads.Malformed(f"grades of {msg.assignment}, which the room did not publish")
            tables = self.grades.setdefault(msg.assignment, {})
            old = tables.get(b.name)
            # A duplicate (QoS 1) or one overtaken within the same boot is dropped; another boot
            # replaces it either way (the broker keeps one connection's order), so a table sent
            # with the bench's stolen login and a boot far ahead lasts until the bench's next one.
            if old is not None and msg.boot == old.boot and msg.seq <= old.seq:
                return False
            tables[b.name] = msg
            self.push_grades(msg.assignment, b.name)
            return False  # the tile has not changed
        # an event
        if b.event_keys.seen((msg.boot, msg.seq)):
            return False  # resent after an outage, seen already
        b.events.append(msg)
        return True

    def push(self, name: str) -> None:
        b = self.benches[name]
        self._was_online[name] = b.online
        text = json.dumps({"type": "bench", "bench": b.view()}, default=str)
        for q in list(self.listeners):
            if q.qsize() < 1000:
                q.put_nowait(text)

    def push_grades(self, aid: str, name: str) -> None:
        """Tell the pages a bench's table of `aid` changed (they fetch the merged table)."""
        text = json.dumps({"type": "grades", "assignment": aid, "bench": name})
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
        self.state = RoomState(lambda name: name in self.enrolled)
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
        self.enrolled: dict[str, Enrolled] = self._load_benches()
        self.enrol_limit = RateLimiter(10, 60.0, 60.0)
        self.client: Any = None
        self._conn = ""  # this room's connection token (payloads.RoomOnline)
        self._stopping = False
        self.loop: asyncio.AbstractEventLoop | None = None
        self.accounts: RoomAccounts | None = None
        self.assignments = RoomAssignments(config.data_dir / "assignments")
        self.collections: dict[str, Collection] = {}
        self.state.on_reply = self._on_reply
        self.state.known_assignment = lambda aid: aid in self.assignments.index
        self.grading_asked: dict[str, dict[str, Any]] = {}  # assignment -> the last grades command
        self._key: sso.Ed25519PrivateKey | None = None
        self._verifiers: dict[tuple[str, str], tuple[str, sso.Verifier]] = {}
        self._tasks: list[asyncio.Task[Any]] = []

    @property
    def key(self) -> sso.Ed25519PrivateKey:
        """The room's signing key (sso.py), made on first use."""
        if self._key is None:
            self._key = sso.room_key(self.config.data_dir)
        return self._key

    def _load_benches(self) -> dict[str, Enrolled]:
        """benches.json; an entry of an enrolment before signed tokens loses its HMAC key (nothing
        honours it any more) and stays, outdated, until the bench is enrolled again."""
        try:
            raw = json.loads(self.benches_path.read_text())
        except (OSError, ValueError):
            return {}
        out: dict[str, Enrolled] = {}
        migrated = False
        for name, entry in raw.items() if isinstance(raw, dict) else ():
            try:
                out[topics.check_bench_name(name)] = Enrolled.model_validate(entry)
            except (ValueError, ValidationError):
                log.error("room: %s: entry %r is not a bench's enrolment; left out", self.benches_path, name[:40])
                continue
            migrated |= isinstance(entry, dict) and "sso_key" in entry
            if out[name].outdated:
                log.warning("room: bench %s was enrolled before signed tokens; %s", name, REENROL)
        if migrated:
            self.enrolled = out
            self._save_benches()
        return out

    def _save_benches(self) -> None:
        text = json.dumps({n: e.model_dump() for n, e in self.enrolled.items()})
        private_write(self.benches_path, text)

    # -- life -----------------------------------------------------------------------------------
    async def start(self) -> None:
        self.loop = asyncio.get_running_loop()
        self.config.data_dir.mkdir(parents=True, exist_ok=True)
        self.files.write()
        _ = self.key
        for name, e in self.enrolled.items():
            b = self.state.bench(name)
            b.url, b.outdated = e.url, e.outdated
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
        self._conn = secrets.token_hex(4)
        c = mqtt.client(endpoint, f"room-{self._conn}", will=self._presence(False))
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
            self._stopping = True
            if self.state.connected:  # a clean goodbye (a disconnect on purpose sends no will)
                info = self.client.publish(*self._presence(False), qos=1, retain=True)
                await asyncio.get_running_loop().run_in_executor(None, lambda: info.wait_for_publish(1.0))
            self.client.disconnect()
            self.client.loop_stop()
        if self.broker is not None:
            await asyncio.get_running_loop().run_in_executor(None, self.broker.stop)

    def _presence(self, online: bool) -> tuple[str, bytes]:
        return topics.ROOM_ONLINE, payloads.RoomOnline.make(online=online, conn=self._conn).wire()

    def _on_mqtt_message(self, _client: Any, _userdata: Any, msg: Any) -> None:
        # paho's network thread: the state is the event loop's, so the message is handed over.
        assert self.loop is not None, "the client starts in start(), after the loop is known"
        if msg.topic == topics.ROOM_ONLINE:
            # An older connection's will (the broker noticed it late) must not leave the benches
            # holding their events while this one listens: say it again.
            try:
                said = (
                    payloads.parse(payloads.ROOM_ONLINE, msg.payload, payloads.BENCH_MAX_BYTES) if msg.payload else None
                )
            except payloads.Malformed:
                said = None
            if (said is None or not said.online) and self.state.connected and not self._stopping:
                _client.publish(*self._presence(True), qos=1, retain=True)
            return
        self.loop.call_soon_threadsafe(self.state.on_message, msg.topic, msg.payload, bool(msg.retain))

    def _on_connect(self, client: Any, _u: Any, _f: Any, reason: Any, _p: Any = None) -> None:
        if not mqtt.reason_ok(reason):
            log.error("room: the broker refused the room: %s", reason)
            return
        client.subscribe([(topics.BENCH_ALL, 1), (topics.ROOM_ONLINE, 1)])
        # After the SUBSCRIBE on the same connection: the broker has the subscription in place when
        # a bench hears this and sends its queued events (payloads.RoomOnline).
        client.publish(*self._presence(True), qos=1, retain=True)
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
            self._send_accounts(self.accounts.current)

    def _send_accounts(self, make: Callable[[], payloads.ClassList | None]) -> None:
        try:
            body = make()
        except ValueError as exc:  # e.g. more accounts than one class list carries: said, not sent
            log.error("room: the class list cannot be published: %s", str(exc)[:300])
            return
        if body is not None and self.client is not None:
            self.client.publish(topics.ACCOUNTS, body.wire(), qos=1, retain=True)

    async def _publish_accounts(self) -> None:
        while True:
            await asyncio.sleep(ACCOUNTS_POLL_S)
            if self.accounts is not None and self.state.connected:
                self._send_accounts(self.accounts.changed)

    # -- assignments and collections ------------------------------------------------------------
    def _republish_assignments(self) -> None:
        for a in self.assignments.list():
            self.publish_assignment(a["id"])

    def publish_assignment(self, aid: str) -> None:
        if self.client is not None:
            self.client.publish(topics.assignment(aid), self.assignments.message(aid).wire(), qos=1, retain=True)

    def bench_token(self, bench: str, token: str, use: str, subject: str) -> None:
        """A bench's own signed token (sso.mint with its private key) for `use` and `subject`,
        checked with the public key it gave at enrolment; 403 for anything else, without saying what."""
        enrolled = self.enrolled.get(bench)
        if enrolled is None or not enrolled.bench_key:
            raise Denied("invalid token")
        cached = self._verifiers.get((bench, use))
        if cached is None or cached[0] != enrolled.bench_key:
            try:
                cached = (enrolled.bench_key, sso.Verifier(sso.load_public(enrolled.bench_key), bench, use))
            except ValueError:
                raise Denied("invalid token") from None
            self._verifiers[(bench, use)] = cached
        try:
            if cached[1].verify(token) != subject:
                raise Denied("invalid token")
        except sso.SsoError:
            raise Denied("invalid token") from None

    def collect(self, aid: str, formats: list[str], wait_s: float, by: str) -> Collection:
        meta = self.assignments.index.get(aid)
        if meta is None:
            raise NotFound(f"no assignment {aid}")
        if self.client is None or not self.state.connected:
            raise Unavailable("the room is not connected to its broker")
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
        body = payloads.Collect.make(
            id=cid, by=by, t=time.time(), collection=cid, assignment=aid, formats=formats
        ).wire()
        self._expect_replies(cid)
        for name, status in c.benches.items():
            if status == "waiting":
                self.client.publish(topics.cmd(name), body, qos=1)
        return c

    def _on_reply(self, bench: str, reply: payloads.Reply) -> None:
        c = self.collections.get(reply.id)
        if c is not None and reply.cmd == "collect" and not reply.ok and c.benches.get(bench) == "waiting":
            c.benches[bench] = "failed"
            c.errors[bench] = reply.error

    def _expect_replies(self, cid: str) -> None:
        """Answers to `cid` are kept (answers to anything else are dropped: RoomState._apply)."""
        self.state.replies[cid] = []
        while len(self.state.replies) > MAX_REPLIES:
            self.state.replies.pop(next(iter(self.state.replies)))

    # -- grading across the benches ---------------------------------------------------------------
    def scenario_path(self, aid: str) -> Path:
        if aid not in self.assignments.index:
            raise NotFound(f"no assignment {aid}")
        return self.config.data_dir / "grading" / aid / "scenario.toml"

    def set_scenario(self, aid: str, text: str) -> Scenario:
        """The room's scenario of `aid`: checked here as far as the room can (syntax, robot, checks;
        the signals against the sources on each bench, which says so in its reply) and sent with
        every grades command, so every bench grades with the same one."""
        path = self.scenario_path(aid)
        scenario = load_scenario(text, f"{aid}.toml", tuple(plants.names()))
        path.parent.mkdir(parents=True, exist_ok=True)
        private_write(path, text)
        return scenario

    def scenario_text(self, aid: str) -> str | None:
        try:
            return self.scenario_path(aid).read_text()
        except FileNotFoundError:
            return None

    def ask_grades(self, aid: str, rerun: bool, by: str) -> dict[str, Any]:
        """Every online enrolled bench sends its table of `aid` (with `rerun`: after grading its own
        students' latest builds, every second while it does); each bench is one command."""
        scenario = self.scenario_text(aid)
        if self.client is None or not self.state.connected:
            raise Unavailable("the room is not connected to its broker")
        online = sorted(n for n in self.enrolled if (b := self.state.benches.get(n)) is not None and b.online)
        cid = secrets.token_hex(8)
        body = payloads.Grade.make(id=cid, by=by, t=time.time(), assignment=aid, rerun=rerun, scenario=scenario)
        self._expect_replies(cid)
        for name in online:
            self.client.publish(topics.cmd(name), body.wire(), qos=1)
        offline = sorted(set(self.enrolled) - set(online))
        self.grading_asked[aid] = {"id": cid, "t": body.t, "rerun": rerun, "benches": online, "offline": offline}
        return {"id": cid, "benches": online, "offline": offline, "scenario": scenario is not None}

    def grades_table(self, aid: str) -> dict[str, Any]:
        """One table of `aid` across the benches: every row of every bench's newest table, with the
        bench it came from and links to that bench's plots and log (its enrolled address, never one a
        message names). A bench that has not sent one, or could not, says why."""
        meta = self.assignments.index.get(aid)
        if meta is None:
            raise NotFound(f"no assignment {aid}")
        tables = self.state.grades.get(aid, {})
        asked = self.grading_asked.get(aid)
        replies = {r["bench"]: r for r in self.state.replies.get(asked["id"], [])} if asked else {}
        checks: list[dict[str, Any]] = []
        ids: list[str] = []
        benches: dict[str, dict[str, Any]] = {}
        rows: list[dict[str, Any]] = []
        total = {"total": 0, "queued": 0, "running": 0, "done": 0}
        for name in sorted(self.enrolled):
            b = self.state.benches.get(name)
            url = self.enrolled[name].url
            reply = replies.get(name)
            entry: dict[str, Any] = {
                "online": bool(b and b.online),
                "url": url,
                "asked": bool(asked and name in asked["benches"]),
                "answered": reply is not None,
                "error": "" if reply is None or reply.get("ok") else str(reply.get("error", "")),
            }
            g = tables.get(name)
            benches[name] = entry
            if g is None:
                continue
            progress = g.progress.model_dump()
            entry.update(t=g.t, progress=progress, rows=len(g.rows), left_out=g.left_out)
            entry["error"] = g.error or entry["error"]
            for k in total:
                total[k] += progress[k]
            mine = [c.id for c in g.checks]
            if not ids:
                ids, checks = mine, [c.model_dump() for c in g.checks]
            entry["same_checks"] = mine == ids or not mine
            for r in g.rows:
                rows.append(
                    {
                        **r.model_dump(),
                        "bench": name,
                        "plots": f"{url}/#grades" if url else "",
                        "log": f"{url}/api/logs/runs/{r.run}" if url and r.run is not None else "",
                    }
                )
        rows.sort(key=lambda r: (r["owner"], r["bench"], r["project"]))
        return {
            "assignment": aid,
            "name": meta["name"],
            "scenario": self.scenario_text(aid) is not None,
            "asked": asked,
            "checks": checks,
            "benches": benches,
            "rows": rows,
            "progress": total,
        }

    def grades_csv(self, aid: str) -> str:
        return table_csv(self.grades_table(aid), extra=("bench",))

    # -- actions --------------------------------------------------------------------------------
    def command(self, bench: str | None, cmd: str, by: str, **fields: Any) -> dict[str, Any]:
        if bench is not None and bench not in self.state.benches:
            raise NotFound(f"no bench {bench}")
        cid = secrets.token_hex(8)
        t = time.time()
        body = payloads.build_command(cmd, id=cid, by=by, t=t, **fields).wire()
        if self.client is None or not self.state.connected:
            raise Unavailable("the room is not connected to its broker")
        self._expect_replies(cid)
        self.client.publish(topics.cmd(bench) if bench else topics.CMD_ALL, body, qos=1)
        return {"id": cid, "t": t, "benches": [bench] if bench else sorted(self.state.benches)}

    def enrol(self, request: EnrolRequest, address: str) -> EnrolAnswer:
        """Record a bench (a new one, or one enrolled again: its old password and key are replaced)
        and give it its broker login and the room's public key."""
        name = topics.check_bench_name(request.name)
        url = check_url(request.url)
        sso.load_public(request.bench_key)  # ValueError: not a key
        password = secrets.token_urlsafe(24)
        self.files.set_password(name, password)
        self.files.reload()
        self.enrolled[name] = Enrolled(
            enrolled=time.time(), address=address[:100], url=url, bench_key=request.bench_key
        )
        self._save_benches()
        self._verifiers.pop((name, "assignment"), None)
        self._verifiers.pop((name, "collect"), None)
        b = self.state.bench(name)
        b.url, b.outdated, b.problem = url, False, ""
        tls = self.config.tls and self.config.broker_tls_port is not None
        return EnrolAnswer.model_validate(
            {
                "name": name,
                "room_key": sso.public_text(self.key),
                "broker": {
                    "host": self.config.broker_names[0],
                    "port": self.config.broker_tls_port if tls else self.config.broker_port,
                    "username": name,
                    "password": password,
                    "ca_pem": self.files.ca_cert.read_text() if tls else "",
                },
            }
        )

    def set_url(self, name: str, url: str) -> Enrolled:
        """An educator changes where a bench's dashboard is (the bench itself cannot)."""
        enrolled = self.enrolled.get(name)
        if enrolled is None:
            raise NotFound(f"no bench {name}")
        enrolled.url = check_url(url)
        self._save_benches()
        b = self.state.bench(name)
        b.url, b.outdated = enrolled.url, enrolled.outdated
        self.state.push(name)
        return enrolled


# ---- routes ---------------------------------------------------------------------------------------

router = APIRouter(prefix="/api/room")


def _room(request: Request | WebSocket) -> Room:
    return request.app.state.room


class Target(BaseModel):
    bench: str | None = Field(default=None, max_length=64, description="a bench's name; none = every bench")


class Message(Target):
    text: str = Field(min_length=1, max_length=500)


class SelfCheck(BaseModel):
    profile: str = Field(default=Settings.sim, pattern=r"^[A-Za-z0-9_.-]{1,64}$")


class BenchAddress(BaseModel):
    url: str = Field(max_length=200, description="the bench's dashboard, http(s)://host[:port]")


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
    from ..server.security import audit

    audit.record(user, "room.join_code", {}, client_address(request))
    return {"code": code, "expires": expires}


# PUBLIC: a bench joining has no account; the one-time code is its credential (rate-limited per address).
@router.post("/enrol", dependencies=[requires(Perm.PUBLIC)])
async def enrol(body: EnrolRequest, request: Request) -> dict[str, Any]:
    room = _room(request)
    address = client_address(request)
    if room.enrol_limit.retry_after(address) > 0:
        raise Busy("too many wrong join codes; wait a minute")
    try:  # before the code is used up: a typo in the address does not cost a code
        topics.check_bench_name(body.name)
        check_url(body.url)
        sso.load_public(body.bench_key)
    except ValueError as exc:
        raise Invalid(str(exc)) from None
    if not room.codes.take(body.code):
        room.enrol_limit.failed(address)
        raise Denied("unknown or expired join code")
    try:
        answer = await asyncio.get_running_loop().run_in_executor(None, room.enrol, body, address)
    except ValueError as exc:
        raise Invalid(str(exc)) from None
    return answer.model_dump()


@router.patch("/benches/{name}", dependencies=[requires(Perm.EDUCATOR)])
async def set_bench_address(
    name: str, body: BenchAddress, request: Request, user: User = Depends(current_user)
) -> dict[str, Any]:
    """Where a bench's dashboard is (what "open bench" links to); recorded at enrolment, changed
    only here or by enrolling the bench again."""
    from ..server.security import audit

    try:
        enrolled = _room(request).set_url(name, body.url)
    except ValueError as exc:
        raise Invalid(str(exc)) from None
    audit.record(user, "room.bench_address", {"bench": name, "url": enrolled.url}, client_address(request))
    return {"name": name, "url": enrolled.url}


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
    busy = [n for n in online if (st := room.state.benches[n].status) is not None and st.active]
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
                b.name for b in room.state.benches.values() if b.status is not None and a["id"] in b.status.assignments
            ),
        }
        for a in room.assignments.list()
    ]


def _publish(request: Request, user: User, meta: dict[str, Any]) -> dict[str, Any]:
    from ..server.security import audit

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
        raise Invalid(f"archive refused: {exc}") from None
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
        raise NotFound(f"no assignment {aid}")
    return FileResponse(room.assignments.archive_path(aid), media_type="application/gzip")


@router.post("/assignments/{aid}/collect", status_code=201, dependencies=[requires(Perm.EDUCATOR)])
async def collect(aid: str, body: Collect, request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    """Ask every enrolled bench for the runs of projects made from `aid`; offline ones are missing.
    Follow ``GET /api/room/collections/<id>`` until ``done``, then download its ``archive``."""
    from ..server.security import audit

    bad = [f for f in body.formats if f not in FORMATS]
    if bad:
        raise Invalid(f"formats: {', '.join(FORMATS)} (not {', '.join(bad)})")
    c = _room(request).collect(aid, sorted(set(body.formats)), body.wait_s, user.username)
    audit.record(user, "room.collect", {"assignment": aid, "collection": c.id}, client_address(request))
    return c.view()


def _collection(request: Request, cid: str) -> Collection:
    c = _room(request).collections.get(cid)
    if c is None:
        raise NotFound(f"no collection {cid}")
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
        raise Conflict("this collection does not wait for this bench (too late, or sent already)")
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
        raise Conflict("benches are still sending; see GET /api/room/collections/" + cid)
    if c.archive is None:
        out = c.folder / "collection.zip"
        await asyncio.to_thread(assemble, c, out)
        c.archive = out
    name = re.sub(r"[^A-Za-z0-9_.-]", "_", c.assignment["name"]) or "assignment"
    return FileResponse(c.archive, media_type="application/zip", filename=f"{name}-runs-{cid[:6]}.zip")


@router.put("/assignments/{aid}/scenario", dependencies=[requires(Perm.EDUCATOR)])
async def put_scenario(aid: str, request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    """The scenario every bench grades `aid` with (docs/educators/grading.md); a refused one is 422
    with its line, as on a bench."""
    from ..server.security import audit

    body = b""
    async for chunk in request.stream():
        body += chunk
        if len(body) > SCENARIO_MAX_BYTES:
            raise TooLarge(f"a scenario is at most {SCENARIO_MAX_BYTES >> 10} KiB")
    s = _room(request).set_scenario(aid, body.decode("utf-8", "replace"))
    audit.record(user, "room.scenario", {"assignment": aid}, client_address(request))
    return {"name": s.name, "robot": s.robot, "points": s.max_points, "checks": [c.id for c in s.checks]}


@router.get("/assignments/{aid}/scenario", dependencies=[requires(Perm.EDUCATOR)])
async def get_scenario(aid: str, request: Request) -> Response:
    text = _room(request).scenario_text(aid)
    if text is None:
        raise NotFound(f"assignment {aid} has no scenario in the room")
    return Response(text, media_type="text/plain; charset=utf-8")


class AskGrades(BaseModel):
    rerun: bool = Field(default=False, description="grade every student's latest build first, on every bench")


@router.post("/assignments/{aid}/grades", status_code=202, dependencies=[requires(Perm.EDUCATOR)])
async def ask_grades(aid: str, body: AskGrades, request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    """Every online bench sends its table of `aid` (with the room's scenario, if it has one); with
    `rerun`, each grades its own students first (its own queue, bounded parallel). Follow
    ``GET .../grades`` (or the page's WebSocket, ``{"type": "grades"}``) for progress."""
    from ..server.security import audit

    room = _room(request)
    if aid not in room.assignments.index:
        raise NotFound(f"no assignment {aid}")
    asked = room.ask_grades(aid, body.rerun, user.username)
    if body.rerun:
        audit.record(
            user, "room.grades_rerun", {"assignment": aid, "benches": asked["benches"]}, client_address(request)
        )
    return asked


@router.get("/assignments/{aid}/grades", dependencies=[requires(Perm.EDUCATOR)])
async def grades(aid: str, request: Request) -> dict[str, Any]:
    return _room(request).grades_table(aid)


@router.get("/assignments/{aid}/grades.csv", dependencies=[requires(Perm.EDUCATOR)])
async def grades_csv(aid: str, request: Request) -> Response:
    return Response(
        _room(request).grades_csv(aid),
        media_type="text/csv",
        headers={"Content-Disposition": f'attachment; filename="room-grades-{aid}.csv"'},
    )


@router.get("/commands/{cid}", dependencies=[requires(Perm.EDUCATOR)])
async def replies(cid: str, request: Request) -> dict[str, Any]:
    return {"id": cid, "replies": _room(request).state.replies.get(cid, [])}


@router.post("/benches/{name}/sso", dependencies=[requires(Perm.EDUCATOR)])
async def sign_on(name: str, request: Request, user: User = Depends(current_user)) -> dict[str, Any]:
    """A link that signs the educator on at the bench's enrolled address (never an address the
    bench's messages name), with a token only the room can sign."""
    room = _room(request)
    enrolled = room.enrolled.get(name)
    if enrolled is None:
        raise NotFound(f"no bench {name}")
    if enrolled.outdated:
        raise Conflict(f"bench {name} was enrolled before the room signed its tokens; {REENROL}")
    token = sso.mint(room.key, name, user.username)
    return {"url": f"{enrolled.url}/room/sso?token={token}"}


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
        from ..server.security import audit as auditmod
        from ..server.security.accounts import Accounts
        from ..server.security.audit import AuditLog
        from ..server.security.auth import bootstrap_admin

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
    http_errors.install(app)
    app.state.settings = settings
    app.state.security = security
    app.state.room = room
    app.add_middleware(SecurityHeaders)
    app.add_middleware(RoomBodyLimit, limit=settings.max_body_bytes, upload_limit=BENCH_MAX + (1 << 20))
    from ..server.http.accounts import router as accounts_router

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
