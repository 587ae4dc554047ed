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
import re
import secrets
import shutil
from pathlib import Path
from typing import Any

from starlette.requests import HTTPConnection

from ..errors import Invalid, NotFound
from ..server.security import audit, ownership
from ..server.security.accounts import User
from ..server.settings import Settings
from ..server.ws.messages import BuildMessage
from . import archive
from .assignments import ORIGIN_PREFIX, Assignments
from .builder import Builder
from .sandbox_config import SandboxConfig
from .store import BuildRow, ProjectRow, ProjectStore, VersionRow
from .versions import Versions

# The appliance's project templates (in <projects_dir>/templates), offered by name.
TEMPLATES = ("base", "20sim")
_SKIP = set(archive.SKIPPED_DIRS)


def clean_name(name: str, fallback: str = "project") -> str:
    """A project name as shown and stored: plain characters, at most 64 (else `fallback`)."""
    name = re.sub(r"[^A-Za-z0-9_.+ -]", "_", name or "").strip(" ._")[:64]
    return name or fallback


def file_list(src: Path) -> list[str]:
    """A source folder's files (relative, sorted), without what an upload leaves out."""
    out = []
    for dirpath, dirnames, filenames in os.walk(src):
        dirnames[:] = sorted(d for d in dirnames if d not in _SKIP)
        for f in sorted(filenames):
            out.append((Path(dirpath) / f).relative_to(src).as_posix())
    return out


def refused(exc: archive.ArchiveRejected) -> Invalid:
    """An archive the checker refused: 422 naming the offending entry."""
    text = f"{exc.entry}: {exc.message}" if exc.entry else exc.message
    detail = {"error": "archive refused: " + text, "entry": exc.entry, "message": exc.message}
    return Invalid("archive refused: " + text, detail=detail)


class VersionLock:
    """A project's version lock (a thread lock: the editor's saves take it in a worker thread),
    taken without blocking the event loop."""

    def __init__(self, versions: Versions, project: ProjectRow) -> None:
        self.lock = versions.lock(project)

    async def __aenter__(self) -> None:
        await asyncio.to_thread(self.lock.acquire)

    async def __aexit__(self, *exc: object) -> None:
        self.lock.release()


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

    def close(self) -> None:
        """At the appliance's stop: the builder's worker ends, then the database is closed (the
        last connection's close checkpoints it and removes projects.sqlite3-wal and -shm, which
        a clean stop used to leave behind)."""
        self.builder.stop()
        self.store.close()

    def folder(self, project: ProjectRow) -> Path:
        return self.root / project.folder

    def src(self, project: ProjectRow) -> Path:
        return self.folder(project) / "src"

    # -- making and changing sources ----------------------------------------------------------------

    def version_lock(self, project: ProjectRow) -> VersionLock:
        return VersionLock(self.versions, project)

    def new_folder(self) -> tuple[str, Path]:
        """A new project's folder (its random token and path), with its builds folder."""
        token = secrets.token_hex(8)
        folder = self.root / token
        folder.mkdir(mode=0o755)
        os.chmod(folder, 0o755)
        (folder / "builds").mkdir(mode=0o755)
        # Explicit: `xrf serve` runs with umask 077 (private data files), and the build user must
        # pass through this folder to its own build folder (search only, as for the folders above).
        os.chmod(folder / "builds", 0o711)
        return token, folder

    async def unpack_into(self, archive_path: Path, folder: Path) -> archive.Manifest:
        """Check + unpack next to the current source, then swap it in; the old source goes. The
        archive is removed either way; a refused one is Invalid (422, the entry named)."""
        new = folder / f"src.new-{secrets.token_hex(4)}"
        try:
            manifest = await asyncio.to_thread(archive.unpack, archive_path, new, self.limits)
        except archive.ArchiveRejected as exc:
            raise refused(exc) from None
        finally:
            archive_path.unlink(missing_ok=True)
        src = folder / "src"
        old = folder / f"src.old-{secrets.token_hex(4)}"
        if src.exists():
            os.rename(src, old)
        os.rename(new, src)
        shutil.rmtree(old, ignore_errors=True)
        return manifest

    async def record(self, project: ProjectRow, author: str, origin: str) -> None:
        """The project's current source as its next version (under its version lock)."""
        async with self.version_lock(project):
            await asyncio.to_thread(self.versions.record, project, author, origin)

    async def from_tree(self, src_t: Path, owner: str, name: str, origin: str) -> ProjectRow:
        """A new project of `owner` whose source is a copy of the folder `src_t`, recorded as version 1."""
        token, folder = self.new_folder()
        await asyncio.to_thread(
            shutil.copytree, src_t, folder / "src", symlinks=False, ignore=shutil.ignore_patterns(*_SKIP)
        )
        files = file_list(folder / "src")
        project = self.store.create_project(owner, name, token, origin)
        project = self.store.update_project(
            project.id, files=len(files), bytes=sum((folder / "src" / f).stat().st_size for f in files)
        )
        await self.record(project, owner, origin)
        return project

    async def provide_assignments(self, owner: str) -> None:
        """A copy of every received assignment this student has not had one of yet (one at a time:
        two pages listing at once make one copy)."""
        async with self.assignment_lock:
            have = self.store.copies_made(owner)
            for a in await asyncio.to_thread(self.assignments.list):
                if a["id"] in have:
                    continue
                project = await self.from_tree(
                    self.assignments.src(a["id"]), owner, clean_name(a["name"], a["id"]), ORIGIN_PREFIX + a["id"]
                )
                self.store.record_copy(a["id"], owner, project.id)
                audit.record(None, "project.create", {"project": project.id, "owner": owner, "assignment": a["id"]})

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
