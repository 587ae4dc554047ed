"""The appliance's ASGI app: API, WebSocket and the dashboard's static files in one process."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request, Response
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles
from uvicorn.middleware.proxy_headers import ProxyHeadersMiddleware

from ..grading.service import GradingService
from ..params.service import ParamsService
from ..projects.service import ProjectsService
from ..room.bench import attach as attach_room
from ..room.bench import router as room_bench_router
from ..room.services import BenchServices
from ..selfcheck_service import SelfCheckService
from ..viz.scene import VizService
from .http import errors as http_errors
from .http import pages as http_pages
from .http import rerun as rerun_http
from .http.accounts import router as accounts_router
from .http.editor import CODEMIRROR_DIR
from .http.editor import router as editor_router
from .http.grading import router as grading_router
from .http.logs import router as logs_router
from .http.params import router as params_router
from .http.projects import router as projects_router
from .http.rerun import router as rerun_router
from .http.ros import router as ros_router
from .http.runs import router, ws_router
from .http.selfcheck import router as selfcheck_router
from .http.system import router as system_router
from .http.viser import router as viser_router
from .http.viz import router as viz_router
from .runs.log_writer import HostLogging
from .runs.ros_bridge import RosBridgeSupervisor
from .runs.store import RunStore
from .runs.supervisor import Supervisor
from .security import ownership
from .security.auth import Perm, Security, SecurityHeaders, optional_user, requires
from .security.body_limit import BodyLimit
from .settings import Settings
from .ws.hub import Hub


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        # Built inside the running loop: the supervisor's locks and events belong to it.
        # Private when we create it (e.g. /var/lib/xrf-lab of a root appliance): the build user is
        # given search permission on the folders down to a build, and only those (projects/build_user.py).
        settings.data_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
        store = RunStore(settings.runs_db)
        hub = Hub(settings.client_queue_telemetry, settings.client_queue_max, settings.slow_client_s)
        supervisor = Supervisor(settings, hub, store)
        hub.add_snapshot(supervisor.snapshot)  # the run and its state first, then the lease (security)
        app.state.supervisor = supervisor
        security.open(hub)  # accounts, audit trail, bench lease (issue 7)
        lease = security.lease
        assert lease is not None  # made by security.open
        hub.add_snapshot(lambda: [lease.message()])
        ownership.attach(hub, supervisor)  # what each WebSocket client may see of the live run
        # The services the routes, the ownership rule and the room's commands are handed (through
        # app.state and the routes' dependencies: projects_of, selfcheck_of): made here, once,
        # never on first use inside a route module.
        app.state.projects = await asyncio.to_thread(ProjectsService, settings, supervisor, asyncio.get_running_loop())
        # Grading (issue 32): assignments' scenarios run on students' builds in the run sandbox,
        # beside the bench (no lease), a bounded queue of them.
        app.state.grading = GradingService(settings, app.state.projects, store, asyncio.get_running_loop())
        selfcheck = SelfCheckService(settings, supervisor)
        app.state.selfcheck = selfcheck
        # The run observers, in the order they are told of a run's start, samples and end
        # (server/runs/lifecycle.py). Host logging first: it adds the log counts to the ended run's record.
        supervisor.lifecycle.register(HostLogging(hub.publish, store))
        # 3D view: viser on 127.0.0.1 (settings.port + 1), reached only through /viser/ (login),
        # fed by the supervisor's reader
        viz = VizService(settings, supervisor)
        supervisor.lifecycle.register(viz)
        await viz.start()
        app.state.viz = viz
        supervisor.lifecycle.register(lease)  # a run's end is the holder's activity
        # Live tuning (issue 28): the run's parameter table when it starts, sets, the change log;
        # every watcher gets the table on connecting and each applied set.
        params = ParamsService(settings, supervisor, hub)
        supervisor.lifecycle.register(params)
        hub.add_snapshot(params.snapshot)
        app.state.params = params
        # ROS 2 bridge per run when enabled (server/runs/ros_bridge.py); its lease gate asks `security`.
        # Registers itself last: one bridge per run, started and stopped with it.
        ros = RosBridgeSupervisor(settings, supervisor, hub, security)
        hub.add_snapshot(ros.snapshot)
        ros.params = params  # `ros2 param set` on the bridge: the same sets, checks and log
        await ros.open()
        app.state.ros = ros
        # The lab room (issue 21): one more listener of the hub once this bench is enrolled (it
        # mirrors what the dashboards hear, alarms, lease and state included, to the room)
        room = await attach_room(
            app, BenchServices(settings, supervisor, security, selfcheck, app.state.projects, app.state.grading)
        )
        # After every observer (lease, ROS bridge) is wired: they hear of the orphaned runs' end.
        recovering = asyncio.create_task(supervisor.recover_orphans(), name="recover-orphans")
        preparing = (
            asyncio.create_task(rerun_http.prepare_viewer_at_start(settings), name="prepare-viewer")
            if settings.prepare_viewer_at_start
            else None
        )
        try:
            yield
        finally:
            with contextlib.suppress(Exception):
                await recovering
            if preparing is not None:  # a stop while preparing: its child killed, its folder removed
                preparing.cancel()
                with contextlib.suppress(BaseException):
                    await preparing
            await room.close()
            selfcheck.close()
            await asyncio.to_thread(app.state.grading.close)
            await ros.close()
            security.close()
            await supervisor.shutdown()
            # After the supervisor: a run's end may still record against a build.
            await asyncio.to_thread(app.state.projects.close)
            await viz.stop()
            from ..logs import rerun_servers  # its rerun child processes (127.0.0.1 servers)

            rerun_servers.stop_rerun_children()
            store.close()

    app = FastAPI(
        title="XRF Lab appliance",
        summary="Run, command and watch firm real-time controllers on an ico-board bench.",
        version="0.1.0",
        lifespan=lifespan,
        # The schema and its browser are behind the login like everything else (routes below).
        openapi_url=None,
        docs_url=None,
        redoc_url=None,
    )
    app.state.settings = settings
    security = Security(settings)
    app.state.security = security
    http_errors.install(app)  # services raise xrflab.errors.XrfError; one handler answers
    app.add_middleware(SecurityHeaders)
    # Added last = outermost: a body is bounded before any other code sees the request.
    app.add_middleware(BodyLimit, limit=settings.max_body_bytes, upload_limit=settings.max_upload_body_bytes)
    if settings.trusted_proxies:
        # Only then is X-Forwarded-For believed, and only from these peers (serve() turns
        # uvicorn's own handling off: it trusted 127.0.0.1, i.e. any local process).
        app.add_middleware(ProxyHeadersMiddleware, trusted_hosts=list(settings.trusted_proxies))
    http_pages.install(app)  # a browser's /users: the dashboard's #users, not the API's JSON 404
    app.include_router(accounts_router)

    # Drawn locally (http/pages.py): a browser asks for it on every page, logged in or not.
    @app.get("/favicon.ico", include_in_schema=False, dependencies=[requires(Perm.PUBLIC)])
    async def favicon() -> Response:
        return http_pages.favicon_response()

    @app.get("/openapi.json", include_in_schema=False, dependencies=[requires(Perm.WATCH)])
    async def openapi_schema() -> JSONResponse:
        return JSONResponse(app.openapi())

    @app.get("/docs", include_in_schema=False, dependencies=[requires(Perm.WATCH)])
    async def api_docs() -> HTMLResponse:
        return get_swagger_ui_html(openapi_url="/openapi.json", title="XRF Lab API")

    app.include_router(router)
    app.include_router(ws_router)
    app.include_router(projects_router)
    app.include_router(editor_router)
    app.include_router(viz_router)
    app.include_router(viser_router)
    app.include_router(logs_router)
    app.include_router(params_router)
    app.include_router(grading_router)
    app.include_router(rerun_router)
    app.include_router(selfcheck_router)
    app.include_router(system_router)
    app.include_router(ros_router)
    app.include_router(room_bench_router)

    frontend = settings.frontend_dir
    if frontend.is_dir():
        # The editor's CodeMirror from the system package (libjs-codemirror, installed by ./lab and
        # deploy/install): served from here, so a student's browser fetches nothing from outside.
        # Mounted before /static, which would answer for this prefix too.
        app.mount(
            "/static/vendor/codemirror", StaticFiles(directory=CODEMIRROR_DIR, check_dir=False), name="codemirror"
        )
        app.mount("/static", StaticFiles(directory=frontend), name="static")

        # PUBLIC so that it can answer a logged-out browser with the login page (a 303): the
        # dashboard itself is only sent to a logged-in user. /static is public (code, no data).
        @app.get("/", include_in_schema=False, dependencies=[requires(Perm.PUBLIC)])
        async def index(request: Request) -> Response:
            if optional_user(request) is None:
                return RedirectResponse("/login", status_code=303)
            # no-cache: a dashboard left open over an upgrade must fetch the new page
            return FileResponse(frontend / "index.html", headers={"Cache-Control": "no-cache"})
    else:

        @app.get("/", include_in_schema=False, dependencies=[requires(Perm.PUBLIC)])
        async def no_frontend() -> RedirectResponse:
            return RedirectResponse("/docs")

    return app
