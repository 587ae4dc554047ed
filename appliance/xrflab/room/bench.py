"""The room on a bench: wired into the appliance once it is enrolled (``xrf room join``).

``RoomLink.open`` is called from the appliance's lifespan; it looks for
``<data>/room/enrolment.json`` (written by ``xrf room join``: enrol.py says who may read it) now
and every few seconds, so joining needs no restart. Once enrolled, the publisher listens to the
hub, commands are handled, the class list is applied, published assignments are received (inline,
or fetched from the room with a token signed by this bench's own key; retried every
``FETCH_RETRY_S`` until they arrive) and ``/room/sso`` signs users in from the room with tokens
checked against the room's public key (sso.py: nothing this bench holds can make one).

Nothing here may stop the bench: the MQTT client reconnects on its own, and a broker or room that
is gone only means the status is not seen (the bench runs on; its events wait in a bounded queue).
"""

from __future__ import annotations

import asyncio
import base64
import logging
import os
import secrets
import shutil
import ssl
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from fastapi import APIRouter, Query, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response

from ..projects.archive import ArchiveRejected
from ..projects.assignments import LIMITS as ASSIGNMENT_LIMITS
from ..projects.assignments import Assignments
from ..server.security.auth import Perm, client_address, requires, set_session_cookies
from ..ticks import until_aligned
from . import mqtt, payloads, sso
from .accounts_sync import BenchAccounts
from .commands import CommandHandler
from .enrol import REENROL, Enrolment, EnrolmentError, Outdated, enrolment_path, read_enrolment
from .publisher import BenchPublisher, RoomRunObserver, next_boot
from .services import BenchServices
from .sso import SsoError, Verifier

log = logging.getLogger(__name__)

ENROL_POLL_S = 2.0
FETCH_RETRY_S = 5.0


def room_folder(data_dir: Path) -> Path:
    return data_dir / "room"


OUTDATED = "this bench was enrolled before the room signed its tokens; " + REENROL


def system_facts(data_dir: Path) -> dict[str, Any]:
    """CPU temperature and throttling where the kernel tells them (a Pi: thermal zone 0 and the
    firmware's get_throttled bits), free disk of the data folder."""
    out: dict[str, Any] = {"cpu_temp_c": None, "throttled": None}
    try:
        out["cpu_temp_c"] = round(int(Path("/sys/class/thermal/thermal_zone0/temp").read_text()) / 1000, 1)
    except (OSError, ValueError):
        pass
    for p in ("/sys/devices/platform/soc/soc:firmware/get_throttled",):
        try:
            out["throttled"] = int(Path(p).read_text().strip(), 16)
        except (OSError, ValueError):
            pass
    try:
        out["disk_free_mb"] = shutil.disk_usage(data_dir).free // (1 << 20)
    except OSError:
        out["disk_free_mb"] = None
    return out


class RoomLink:
    def __init__(self, services: BenchServices) -> None:
        self.services = services
        self.settings = services.settings
        self.folder = room_folder(self.settings.data_dir)
        self.publisher: BenchPublisher | None = None
        self.run_observer: RoomRunObserver | None = None
        self.verifier: Verifier | None = None
        self.accounts: BenchAccounts | None = None
        self._poll: asyncio.Task[None] | None = None
        self._last_cycles: tuple[float, int] | None = None
        self.name = ""
        self.key: sso.Ed25519PrivateKey | None = None  # this bench's own: its tokens to the room
        self.outdated = False  # enrolled before signed tokens: no sign-on, fetch or upload
        self.room_url = ""
        self.ca_pem = ""
        self.assignments = Assignments(self.settings.data_dir / "assignments")
        self._wanted: dict[str, payloads.Assignment] = {}  # published here, not received yet
        self._problem = ""
        self._receiving: set[str] = set()
        self._tasks: set[asyncio.Task[Any]] = set()

    async def open(self) -> None:
        if not self._try_start():
            self._poll = asyncio.get_running_loop().create_task(self._wait_for_enrolment(), name="room-enrolment")

    async def _wait_for_enrolment(self) -> None:
        # Until `xrf room join` writes the file: one stat of a name made once, not the whole
        # read's paths and open each poll (a tenth of the idle appliance's event loop, session 16).
        # Once the name is there, the whole read every poll, as before (a file that is not
        # usable yet is said once and looked at again).
        path = os.fspath(enrolment_path(self.settings.data_dir))
        while True:
            # on the appliance's whole seconds, with its other periodic work (issue 30 item 4)
            await asyncio.sleep(until_aligned(ENROL_POLL_S))
            try:
                os.lstat(path)
            except FileNotFoundError:
                continue
            except OSError:
                pass  # not ours to read, say: read_enrolment says why
            if self._try_start():
                return

    def _try_start(self) -> bool:
        try:
            enrolment = read_enrolment(self.settings.data_dir)
            if enrolment is not None:
                self._start(enrolment)
        except Exception as exc:
            problem = str(exc) if isinstance(exc, EnrolmentError) else f"cannot start: {exc}"
            if problem != self._problem:  # said once, not at every poll
                self._problem = problem
                log.error("room: %s", problem, exc_info=not isinstance(exc, EnrolmentError))
            return False
        return enrolment is not None

    def _start(self, e: Enrolment | Outdated) -> None:
        services = self.services
        b = e.broker
        endpoint = mqtt.Endpoint(b.host, b.port, b.username, b.password, b.ca_pem)
        security = services.security
        if isinstance(e, Enrolment):
            room_key, own_key = sso.load_public(e.room_key), sso.load_private(e.bench_key)  # both, or neither
            self.verifier, self.key = Verifier(room_key, e.name, "sso"), own_key
        else:
            self.outdated = True
            log.error("room: %s", OUTDATED)
        self.accounts = BenchAccounts(security, self.folder)
        self.name, self.room_url = e.name, e.room_url
        self.ca_pem = b.ca_pem
        handler = CommandHandler(services, self, asyncio.get_running_loop())
        self.publisher = BenchPublisher(
            e.name,
            endpoint,
            next_boot(self.folder),
            self.facts,
            on_command=handler,
            on_accounts=self._on_accounts,
            on_assignment=self._on_assignment,
        )
        self.publisher.status["assignments"] = [a["id"] for a in self.assignments.list()]
        handler.publisher = self.publisher
        self._spawn(self._retry_assignments())
        self.run_observer = RoomRunObserver(self.publisher)
        services.supervisor.lifecycle.register(self.run_observer)
        services.supervisor.hub.listeners.append(self.publisher.on_hub)
        self.publisher.start()
        log.warning("room: bench %s reports to %s:%s", e.name, b.host, b.port)

    def _on_accounts(self, body: payloads.ClassList) -> None:
        if self.accounts is not None:
            self.accounts.apply(body)
            if self.publisher is not None:
                self.publisher.status["accounts_version"] = self.accounts.version
                self.publisher.status_changed()

    # -- assignments (the event loop) ------------------------------------------------------------
    def _spawn(self, coro: Any) -> None:
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _on_assignment(self, body: payloads.Assignment) -> None:
        aid = body.id  # checked by the model (payloads.Assignment)
        self._wanted[aid] = body
        if aid not in self._receiving:
            self._spawn(self._receive(aid))

    async def _retry_assignments(self) -> None:
        """What could not be fetched (the room down, a network hiccup) is fetched again."""
        while True:
            await asyncio.sleep(FETCH_RETRY_S)
            for aid in list(self._wanted):
                if aid not in self._receiving:
                    self._spawn(self._receive(aid))

    async def _receive(self, aid: str) -> None:
        body = self._wanted.get(aid)
        if body is None:
            return
        self._receiving.add(aid)
        tmp = self.assignments.root / f".dl-{aid}-{secrets.token_hex(4)}"
        try:
            if await asyncio.to_thread(self.assignments.has, aid, body.sha256):
                self._wanted.pop(aid, None)
                return
            self.assignments.root.mkdir(parents=True, exist_ok=True)
            if body.inline is not None:
                tmp.write_bytes(base64.b64decode(body.inline, validate=True))
            else:
                await asyncio.to_thread(self._fetch, aid, body.path, tmp)
            info = await asyncio.to_thread(self.assignments.install, body.model_dump(), tmp)
        except (ValueError, ArchiveRejected) as exc:  # refused for good: not fetched again
            self._wanted.pop(aid, None)
            log.error("room: assignment %s refused: %s", aid, exc)
            return
        except Exception as exc:  # the room or the network: fetched again later
            log.warning("room: assignment %s not received yet (%s); trying again", aid, exc)
            return
        finally:
            self._receiving.discard(aid)
            tmp.unlink(missing_ok=True)
        self._wanted.pop(aid, None)
        log.warning("room: assignment %s (%s) received", aid, info["name"])
        if self.publisher is not None:
            self.publisher.status["assignments"] = [a["id"] for a in self.assignments.list()]
            self.publisher.event("assignment", id=aid, name=info["name"])
            self.publisher.status_changed()

    def _http(self, timeout: float) -> Any:
        """An HTTP client towards the room: its TLS checked with the system's CAs and the room's own."""
        import httpx

        ctx = ssl.create_default_context()
        if self.ca_pem:
            ctx.load_verify_locations(cadata=self.ca_pem)
        return httpx.Client(base_url=self.room_url, timeout=timeout, verify=ctx)

    def _token(self, subject: str, use: str) -> dict[str, str]:
        if self.key is None:
            raise RuntimeError(OUTDATED)
        return {"bench": self.name, "token": sso.mint(self.key, self.name, subject, ttl_s=sso.TTL_S, use=use)}

    def _fetch(self, aid: str, path: str, out: Path) -> None:
        """An assignment too large for MQTT, from the room (blocking; bounded as an upload is)."""
        if not self.room_url or path != f"/api/room/assignments/{aid}/archive":
            raise RuntimeError("no room address to fetch the assignment from (enrolled by an old xrf room join?)")
        total = 0
        with self._http(120) as c, c.stream("GET", path, params=self._token(aid, "assignment")) as r:
            if r.status_code != 200:
                raise RuntimeError(f"the room answered {r.status_code}")
            with open(out, "wb") as f:
                for chunk in r.iter_bytes():
                    total += len(chunk)
                    if total > ASSIGNMENT_LIMITS.max_upload:
                        raise ValueError("the assignment is larger than a bench accepts")
                    f.write(chunk)

    def upload_collection(self, cid: str, path: Path) -> None:
        """A packed collection to the room (blocking)."""
        if not self.room_url:
            raise RuntimeError("no room address to upload to (enrolled by an old xrf room join?)")

        def chunks() -> Iterator[bytes]:
            with open(path, "rb") as f:
                yield from iter(lambda: f.read(1 << 20), b"")

        with self._http(600) as c:
            r = c.post(
                f"/api/room/collections/{cid}/benches/{self.name}",
                params=self._token(cid, "collect"),
                content=chunks(),
                headers={"Content-Type": "application/gzip"},
            )
        if r.status_code != 200:
            raise RuntimeError(f"the room refused the upload: {r.status_code} {r.text[:200]}")

    def facts(self) -> dict[str, Any]:
        """Asked once a second by the publisher: the loop's counters, the lease, the machine."""
        sup = self.services.supervisor
        st = sup.state_payload()
        run = sup.current
        last = run.last_status if run is not None else None
        cycles = int(getattr(last, "cycles", 0) or 0)
        now = time.monotonic()
        rate = None
        if self._last_cycles is not None and run is not None and run.alive:
            dt = now - self._last_cycles[0]
            if dt > 0:
                rate = round(max(0, cycles - self._last_cycles[1]) / dt, 1)
        self._last_cycles = (now, cycles)
        lease = self.services.security.lease
        holder = lease.holder.user.username if lease is not None and lease.holder is not None else ""
        row = run.row if run is not None else sup.last_row
        return {
            "state": st.get("name", "NO RUN"),
            "active": bool(st.get("active")),
            "run_id": row.id if row else None,
            "run_owner": row.owner if row else "",
            "cycles": cycles,
            "misses": int(getattr(last, "missed", 0) or 0) if last else (row.misses if row else 0),
            "cycle_rate": rate,
            "cycle_freq": row.cycle_freq if row else None,
            "holder": holder,
            "accounts_version": self.accounts.version if self.accounts else 0,
            **system_facts(self.settings.data_dir),
        }

    async def close(self) -> None:
        if self._poll:
            self._poll.cancel()
        for t in list(self._tasks):
            t.cancel()
        if self.publisher is not None:
            try:
                self.services.supervisor.hub.listeners.remove(self.publisher.on_hub)
            except ValueError:
                pass
            if self.run_observer is not None:
                self.services.supervisor.lifecycle.unregister(self.run_observer)
            await self.publisher.stop()


router = APIRouter()


# PUBLIC because it is how a user without a session on this bench gets one: the signed token is
# the credential (sso.py). Anything wrong answers 403 without saying more.
@router.get("/room/sso", include_in_schema=False, dependencies=[requires(Perm.PUBLIC)])
async def room_sso(request: Request, token: str = Query("", max_length=1000)) -> Response:
    from ..server.security import audit

    link: RoomLink | None = getattr(request.app.state, "room", None)
    security = request.app.state.security
    if link is not None and link.outdated:
        return HTMLResponse(OUTDATED, status_code=404)
    if link is None or link.verifier is None or security.accounts is None:
        return HTMLResponse("this bench is not enrolled in a room", status_code=404)
    try:
        username = link.verifier.verify(token)
    except SsoError as exc:
        return HTMLResponse(str(exc), status_code=403)
    user = security.accounts.by_name(username)
    # only the room's own accounts: a bench account of the same name (its local admin) is not the room's
    owned = link.accounts is not None and username in link.accounts.state.get("owned", [])
    if user is None or user.disabled or not owned:
        audit.record(None, "auth.failed", {"username": username[:64], "via": "room"}, client_address(request))
        return HTMLResponse("invalid sign-on link", status_code=403)
    token_, csrf = security.accounts.new_session(user, client_address(request))
    audit.record(user, "auth.login", {"via": "room"}, client_address(request))
    response = RedirectResponse("/", status_code=303)
    set_session_cookies(request, response, token_, csrf, int(security.accounts.session_max_s))
    return response


async def attach(app: Any, services: BenchServices) -> RoomLink:
    """From the appliance's lifespan: enrolled now or later, the bench joins its room. The link is
    kept in the app's state for the sign-on route above (a route reaches services that way)."""
    link = RoomLink(services)
    app.state.room = link
    await link.open()
    return link
