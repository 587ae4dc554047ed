"""The appliance's ASGI app: API, WebSocket and the dashboard's static files in one process."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from fastapi.responses import FileResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles

from .api import router, ws_router
from .routes_projects import router as projects_router
from .hub import Hub
from .routes_logs import router as logs_router
from .runs import RunStore
from .settings import Settings
from .supervisor import Supervisor


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        # Built inside the running loop: the supervisor's locks and events belong to it.
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        store = RunStore(settings.runs_db)
        hub = Hub(settings.client_queue_telemetry, settings.client_queue_max, settings.slow_client_s)
        supervisor = Supervisor(settings, hub, store)
        hub.snapshot = supervisor.snapshot
        app.state.supervisor = supervisor
        try:
            yield
        finally:
            await supervisor.shutdown()
            store.close()

    app = FastAPI(
        title="XRF Lab appliance",
        summary="Run, command and watch firm real-time controllers on an ico-board bench.",
        version="0.1.0",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.include_router(router)
    app.include_router(ws_router)
    app.include_router(projects_router)
    app.include_router(logs_router)

    frontend = settings.frontend_dir
    if frontend.is_dir():
        app.mount("/static", StaticFiles(directory=frontend), name="static")

        @app.get("/", include_in_schema=False)
        async def index() -> FileResponse:
            # no-cache: a dashboard left open over an upgrade must fetch the new page
            return FileResponse(frontend / "index.html", headers={"Cache-Control": "no-cache"})
    else:

        @app.get("/", include_in_schema=False)
        async def no_frontend() -> RedirectResponse:
            return RedirectResponse("/docs")

    return app
