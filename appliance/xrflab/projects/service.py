"""The projects service: students' projects on disk and in their database, their versions, the
build queue and the assignments the room published. One per appliance, made in the app's lifespan
(server/app.py) and handed to whoever needs it: the project and editor routes (through the
`projects_of` dependency), the run routes (a student's own builds), the ownership rule (may this
user start that build) and the room's commands (collecting an assignment's runs).

It was made lazily inside the projects routes before, so the room and the ownership rule imported
a routes module to reach it (and made an import cycle of it). A service, above the projects'
domain modules (store, builder, versions, assignments) and beside the runs and security services.
"""

from __future__ import annotations

import asyncio
import os
from pathlib import Path
from typing import Any

from starlette.requests import HTTPConnection

from ..errors import NotFound
from ..server.security import audit, ownership
from ..server.security.accounts import User
from ..server.settings import Settings
from ..server.ws.messages import BuildMessage
from . import archive
from .assignments import Assignments
from .builder import Builder
from .sandbox_config import SandboxConfig
from .store import BuildRow, ProjectRow, ProjectStore, VersionRow
from .versions import Versions

# The appliance's project templates (in <projects_dir>/templates), offered by name.
TEMPLATES = ("base", "20sim")


class ProjectsService:
    def __init__(self, settings: Settings, supervisor: Any, loop: asyncio.AbstractEventLoop) -> None:
        self.settings = settings
        self.supervisor = supervisor
        self.root: Path = settings.data_dir / "projects"
        self.root.mkdir(parents=True, exist_ok=True)
        os.chmod(self.root, 0o711)  # passable (the build user needs its project), not listable
        (self.root / ".incoming").mkdir(exist_ok=True)
        os.chmod(self.root / ".incoming", 0o700)
        self.store = ProjectStore(settings.data_dir / "projects.sqlite3")
        hub = supervisor.hub
        self.limits = archive.Limits()

        # Build messages carry their project's `owner`: the hub gives them to the owner's (and
        # educators') WebSockets only (ownership.scope): one student's compiler output is nobody
        # else's business. The builder names the kind (always `build`); the model checks it.
        def publish(kind: str, payload: dict[str, Any]) -> None:
            message = BuildMessage.model_validate({**payload, "type": kind})
            try:
                loop.call_soon_threadsafe(hub.publish, message)
            except RuntimeError:  # loop closed: the appliance is stopping
                pass

        self.builder = Builder(
            self.store, self.root, publish, SandboxConfig.from_settings(settings), hide_dir=settings.data_dir
        )
        # Every change of a project's source is a version; a build compiles a version's tree.
        self.versions = Versions(self.store, self.root)
        # What the room published (issue 21): templates of this bench's, copied to every student.
        self.assignments = Assignments(settings.data_dir / "assignments")
        self.assignment_lock = asyncio.Lock()

    def folder(self, project: ProjectRow) -> Path:
        return self.root / project.folder

    def src(self, project: ProjectRow) -> Path:
        return self.folder(project) / "src"

    # -- whose --------------------------------------------------------------------------------------

    def project_for(self, user: User | None, pid: int) -> ProjectRow:
        """The project if `user` may see it; someone else's is NotFound, like a missing one."""
        return ownership.require(user, self.store.project(pid), lambda p: p.owner, "project", pid)

    def build_for(self, user: User | None, pid: int, bid: int) -> tuple[ProjectRow, BuildRow]:
        project = self.project_for(user, pid)
        b = self.store.build(bid)
        if b is None or b.project_id != project.id:
            raise NotFound(f"no build {bid} of project {pid}")
        return project, b

    # -- builds -------------------------------------------------------------------------------------

    def build_dict(self, b: BuildRow, reused: bool = False) -> dict[str, Any]:
        """A build as the API's Build record: the row, whether it was reused, its queue place."""
        d = b.as_dict()
        d["reused"] = reused
        d["position"] = self.builder.position(b.id) if b.status in ("queued", "building") else -1
        return d

    async def submit(
        self, project: ProjectRow, version: VersionRow, user: User | None, address: str
    ) -> tuple[BuildRow, bool]:
        """Queue the build of one source version (its immutable tree, so the build compiles exactly
        that source however the project is edited meanwhile); an unchanged source reuses its build."""
        row, reused = await asyncio.to_thread(self.builder.submit, project, self.versions.tree(project, version))
        self.store.update_project(project.id, source_hash=row.source_hash)
        detail = {"project": project.id, "build": row.id, "reused": reused, "version": version.n}
        audit.record(user, "build.start", detail, address)
        return row, reused


def projects_of(conn: HTTPConnection) -> ProjectsService:
    """FastAPI dependency: the app's projects service (made in server/app.py's lifespan)."""
    svc: ProjectsService = conn.app.state.projects
    return svc
