"""Student projects: upload (checked, then unpacked), new from a template, download, build in the
sandbox, see the build's output and errors, run a build on the bench.

Every route declares PROJECTS (DRIVE to start a run) and every project route checks ownership:
a project that is not the requester's answers 404, exactly like one that does not exist. The
owner is the username (as in the runs table); the rule is server/security/ownership.py's (educators see
everything), for the routes and for the build messages on the WebSocket alike.

The projects service (xrflab/projects/service.py: store, build queue, versions, assignments) is
made in the app's lifespan (server/app.py); these routes reach it through ``projects_of``.
"""

from __future__ import annotations

import asyncio
import io
import mmap
import os
import re
import shutil
import zipfile
from pathlib import Path
from typing import Any, Literal

from fastapi import APIRouter, Depends, Request
from fastapi.responses import PlainTextResponse, Response
from pydantic import BaseModel, Field

from ...errors import Conflict, NotFound, TooLarge, XrfError
from ...plant_field import PlantName
from ...projects import archive, source, twentysim
from ...projects.assignments import ORIGIN_PREFIX
from ...projects.service import TEMPLATES, ProjectsService, clean_name, file_list, projects_of
from ...projects.store import BuildRow, ProjectRow, RunLinkRow
from ...records import list_of
from ..runs import start as run_start
from ..security import audit, ownership
from ..security import auth as authmod
from ..security.auth import Perm, requires
from ..security.body_limit import spool_to_file

router = APIRouter(prefix="/api", tags=["projects"])
SOURCE_MAX_BYTES = 1 << 20


def _audit(request: Request, action: str, detail: dict[str, Any]) -> None:
    """The audit trail (issue 7): who uploaded, built and ran what."""
    audit.record(_user(request), action, detail, authmod.client_address(request))


# ---- who ------------------------------------------------------------------------------------------


def _user(request: Request) -> Any:
    return ownership.user_of(request)


def _owner_name(user: Any) -> str:
    return str(user.username)


def _project(request: Request, pid: int) -> tuple[ProjectsService, ProjectRow]:
    svc = projects_of(request)
    return svc, svc.project_for(_user(request), pid)


def _build(request: Request, pid: int, bid: int) -> tuple[ProjectsService, ProjectRow, BuildRow]:
    svc = projects_of(request)
    return svc, *svc.build_for(_user(request), pid, bid)


# ---- models ---------------------------------------------------------------------------------------


# The API's project records are made from their one definition in projects/store.py (ProjectRow,
# BuildRow, VersionRow, RunLinkRow: SQL columns and API fields alike), plus what these routes add;
# tests/projects/test_project_record.py compares them with the tables and /openapi.json.
Project = ProjectRow.api_model("Project")
Build = BuildRow.api_model(
    "Build",
    reused=(bool, Field(default=False, description="an unchanged source: this earlier build is the answer")),
    position=(int, Field(default=-1, description="queued or building: place in the build queue; else -1")),
)
ProjectRun = RunLinkRow.api_model("ProjectRun")
ProjectDetail = ProjectRow.api_model(
    "ProjectDetail",
    twenty_sim=(
        dict[str, Any] | None,
        Field(description="step size, integration method, inputs/outputs from the tokens"),
    ),
    messages=(dict[str, Any], Field(description="Ros2Xeno / Xeno2Ros fields from msg/")),
    package=(
        dict[str, str] | None,
        Field(description="a workspace: the controller package it builds ({path, name}); else null"),
    ),
    file_list=(list[str], ...),
    builds=(list_of(Build), Field(description="the newest 20 builds")),
    runs=(list_of(ProjectRun), ...),
)


class UploadResult(BaseModel):
    project: Project  # type: ignore[valid-type]  # a model made at import (ProjectRow.api_model)
    format: str
    files: int
    bytes: int
    stripped_folder: str
    skipped: list[str]
    package: str = Field(description="a workspace: the controller package chosen in it (its path); else ''")


class UploadRules(BaseModel):
    """What an upload may be and hold (projects/archive.py rules(): the check's own definitions)."""

    formats: list[str]
    layouts: list[str]
    max_upload: int = Field(description="bytes of the archive")
    max_total: int = Field(description="bytes of all files, unpacked")
    max_file: int = Field(description="bytes of one file, unpacked")
    max_files: int = Field(description="files and folders")
    left_out: list[str] = Field(description="folders never unpacked (build output, version control)")


class FromTemplate(BaseModel):
    template: str = Field(
        pattern=r"^(base|20sim|assignment:[a-z0-9][a-z0-9-]{0,39})$",
        description="base, 20sim or assignment:<id> (one the room published)",
    )
    name: str = Field(default="", max_length=64)


class RunBuild(BaseModel):
    sim: PlantName | None = None
    max_cycles: int | None = Field(default=None, ge=1)
    log_timing: bool = Field(default=False, description="as POST /api/runs (the Bench page starts project builds here)")


class Excerpt(BaseModel):
    path: str
    first: int
    lines: list[str]
    total: int
    highlight: int | None


# ---- helpers --------------------------------------------------------------------------------------


def _described(src: Path) -> dict[str, Any]:
    """The 20-sim model and the message fields of the controller the source builds (for an XRF2
    workspace: its controller package, the messages from its XRF2 folder or xrf2_msgs package)."""
    located = source.locate(src)
    path, name = source.package_of(located) if located else ("", "")
    return {
        "twenty_sim": twentysim.describe(located.project if located else src),
        "messages": source.message_fields(src, located),
        "package": {"path": path, "name": name} if path else None,
    }


def _multipart(body: Path, boundary: bytes, out: Path) -> tuple[str, dict[str, str]]:
    """The first file part of a multipart/form-data body copied to ``out``; (filename, other fields)."""
    fields: dict[str, str] = {}
    filename = ""
    if body.stat().st_size == 0:
        raise ValueError("empty request body")
    with open(body, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
        delim = b"--" + boundary
        pos = mm.find(delim)
        while pos != -1:
            start = pos + len(delim)
            if mm[start : start + 2] == b"--":
                break
            head_end = mm.find(b"\r\n\r\n", start)
            if head_end == -1:
                raise ValueError("malformed multipart body")
            headers = mm[start:head_end].decode("utf-8", "replace")
            data_start = head_end + 4
            nxt = mm.find(b"\r\n" + delim, data_start)
            if nxt == -1:
                raise ValueError("malformed multipart body (no closing boundary)")
            disp = next((h for h in headers.split("\r\n") if h.lower().startswith("content-disposition")), "")
            fm = re.search(r'filename="([^"]*)"', disp)
            nm = re.search(r'\bname="([^"]*)"', disp)
            if fm and not filename:
                filename = fm.group(1)
                with open(out, "wb") as o:
                    for at in range(data_start, nxt, 1 << 20):
                        o.write(mm[at : min(at + (1 << 20), nxt)])
            elif nm and nxt - data_start < 4096:
                fields[nm.group(1)] = mm[data_start:nxt].decode("utf-8", "replace")
            pos = nxt + 2
    if not filename and not out.exists():
        raise ValueError("no file in the upload (send it as a form field with a filename)")
    return filename, fields


async def _receive_archive(request: Request, svc: ProjectsService) -> tuple[Path, str, dict[str, str]]:
    incoming = svc.root / ".incoming"
    limit = svc.limits.max_upload + (1 << 16)
    body = await spool_to_file(
        request,
        incoming,
        limit,
        too_large={"error": f"the upload is over {limit >> 20} MB", "entry": "", "message": ""},
    )
    ctype = request.headers.get("content-type", "")
    if ctype.startswith("multipart/form-data"):
        m = re.search(r"boundary=\"?([^\";]+)\"?", ctype)
        if not m:
            body.unlink()
            raise XrfError("multipart upload without a boundary", 400)
        out = body.with_name(body.name + ".archive")
        try:
            filename, fields = await asyncio.to_thread(_multipart, body, m.group(1).encode(), out)
        except ValueError as exc:
            out.unlink(missing_ok=True)
            raise XrfError(str(exc), 400) from None
        finally:
            body.unlink(missing_ok=True)
        return out, filename, fields
    return body, request.query_params.get("filename", ""), {}


def _zip_dir(src: Path, top: str) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for rel in file_list(src):
            p = src / rel
            if p.is_symlink() or not p.is_file():
                continue
            z.write(p, f"{top}/{rel}")
    return buf.getvalue()


def _download(data: bytes, name: str) -> Response:
    return Response(
        data, media_type="application/zip", headers={"Content-Disposition": f'attachment; filename="{name}.zip"'}
    )


# ---- routes ---------------------------------------------------------------------------------------


@router.get("/projects", response_model=list_of(Project), dependencies=[requires(Perm.PROJECTS)])
async def list_projects(
    request: Request, all: bool = False, svc: ProjectsService = Depends(projects_of)
) -> list[dict[str, Any]]:
    """The requester's projects; an educator's own too, or with ``all=true`` everyone's. A student
    finds a copy of every assignment the room published here (made on the first listing)."""
    user = _user(request)
    if user is not None and not user.is_educator:
        await svc.provide_assignments(_owner_name(user))
    rows = svc.store.projects() if all else svc.store.projects(owner=_owner_name(user))
    return [p.as_dict() for p in ownership.visible(user, rows)]


@router.post("/projects", response_model=UploadResult, status_code=201, dependencies=[requires(Perm.PROJECTS)])
async def upload_project(
    request: Request, name: str = "", svc: ProjectsService = Depends(projects_of)
) -> dict[str, Any]:
    """Upload a project as zip / tar / tar.gz: multipart/form-data (field ``file``, optional
    ``name``) or the archive as the raw body. Checked completely before anything is unpacked;
    a refusal (422) names the offending entry."""
    archive_path, filename, fields = await _receive_archive(request, svc)
    base = Path(filename).name if filename else ""
    base = next((base[: -len(x)] for x in archive.SUFFIXES if base.endswith(x)), base)
    token, folder = svc.new_folder()
    try:
        manifest = await svc.unpack_into(archive_path, folder)
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    # A workspace is named after the controller package chosen in it, not its top folder ("src").
    pname = clean_name(name or fields.get("name", "") or manifest.package_name or manifest.prefix or base)
    project = svc.store.create_project(_owner_name(_user(request)), pname, token, "upload")
    project = svc.store.update_project(project.id, files=len(manifest.files), bytes=manifest.total)
    await svc.record(
        project, _owner_name(_user(request)), "upload " + (Path(filename).name if filename else "(archive)")
    )
    _audit(request, "project.upload", {"project": project.id, "name": project.name, "files": len(manifest.files)})
    return _upload_result(project, manifest)


def _upload_result(project: ProjectRow, manifest: archive.Manifest) -> dict[str, Any]:
    """What an upload (the first or a new version) answers: UploadResult."""
    return {
        "project": project.as_dict(),
        "format": manifest.format,
        "files": len(manifest.files),
        "bytes": manifest.total,
        "stripped_folder": manifest.prefix,
        "skipped": manifest.skipped,
        "package": manifest.package,
    }


@router.put("/projects/{pid}/source", response_model=UploadResult, dependencies=[requires(Perm.PROJECTS)])
async def replace_source(pid: int, request: Request) -> dict[str, Any]:
    """A new version of the project's source (same rules as the first upload); builds are kept."""
    svc, project = _project(request, pid)
    archive_path, filename, _ = await _receive_archive(request, svc)
    # Under the project's version lock: an editor save never lands between the swap and its record.
    async with svc.version_lock(project):
        manifest = await svc.unpack_into(archive_path, svc.folder(project))
        project = svc.store.update_project(project.id, files=len(manifest.files), bytes=manifest.total)
        await asyncio.to_thread(
            svc.versions.record,
            project,
            _owner_name(_user(request)),
            "upload " + (Path(filename).name if filename else "(archive)"),
        )
    _audit(request, "project.upload", {"project": project.id, "name": project.name, "files": len(manifest.files)})
    return _upload_result(project, manifest)


@router.get("/project-upload-rules", response_model=UploadRules, dependencies=[requires(Perm.PROJECTS)])
async def upload_rules(svc: ProjectsService = Depends(projects_of)) -> dict[str, Any]:
    """What an upload may be and hold: the Projects page says it before an upload."""
    return archive.rules(svc.limits)


@router.get("/project-templates", dependencies=[requires(Perm.PROJECTS)])
async def list_templates(request: Request, svc: ProjectsService = Depends(projects_of)) -> list[dict[str, Any]]:
    """The appliance's templates, then the assignments the room published (``assignment:<id>``)."""
    root = request.app.state.settings.projects_dir / "templates"
    out: list[dict[str, Any]] = []
    for t in TEMPLATES:
        readme = root / t / "README.md"
        first = readme.read_text(errors="replace").strip().splitlines()[0].lstrip("# ") if readme.exists() else t
        out.append({"name": t, "title": first})
    for a in await asyncio.to_thread(svc.assignments.list):
        out.append(
            {
                "name": ORIGIN_PREFIX + a["id"],
                "title": a["name"],
                "assignment": True,
                "by": a.get("by", ""),
                "published": a.get("t"),
            }
        )
    return out


@router.get("/project-templates/{template}/download", dependencies=[requires(Perm.PROJECTS)])
async def download_template(template: Literal["base", "20sim"], request: Request) -> Response:
    src = request.app.state.settings.projects_dir / "templates" / template
    return _download(await asyncio.to_thread(_zip_dir, src, f"my_{template}"), f"my_{template}")


@router.post("/projects/from-template", response_model=Project, status_code=201, dependencies=[requires(Perm.PROJECTS)])
async def new_from_template(
    body: FromTemplate, request: Request, svc: ProjectsService = Depends(projects_of)
) -> dict[str, Any]:
    if body.template.startswith(ORIGIN_PREFIX):
        aid = body.template[len(ORIGIN_PREFIX) :]
        meta = svc.assignments.get(aid)
        if meta is None:
            raise NotFound(f"no assignment {aid}")
        src_t, default, origin = svc.assignments.src(aid), clean_name(meta["name"], aid), body.template
    else:
        src_t = request.app.state.settings.projects_dir / "templates" / body.template
        default, origin = f"my_{body.template}", f"template:{body.template}"
    project = await svc.from_tree(src_t, _owner_name(_user(request)), clean_name(body.name, default), origin)
    _audit(request, "project.create", {"project": project.id, "name": project.name, "template": body.template})
    return project.as_dict()


@router.get("/projects/{pid}", response_model=ProjectDetail, dependencies=[requires(Perm.PROJECTS)])
async def get_project(pid: int, request: Request) -> dict[str, Any]:
    svc, project = _project(request, pid)
    src = svc.src(project)
    return {
        **project.as_dict(),
        **(await asyncio.to_thread(_described, src)),
        "file_list": file_list(src)[:2000],
        "builds": [svc.build_dict(b) for b in svc.store.builds(pid, 20)],
        "runs": svc.store.runs_of(pid),
    }


@router.delete("/projects/{pid}", status_code=204, dependencies=[requires(Perm.PROJECTS)])
async def delete_project(pid: int, request: Request) -> Response:
    svc, project = _project(request, pid)
    if any(b.status in ("queued", "building") for b in svc.store.builds(pid, 5)):
        raise Conflict("a build of this project is queued or running; wait for it")
    _audit(request, "project.delete", {"project": pid})
    svc.store.delete_project(pid)
    await asyncio.to_thread(shutil.rmtree, svc.folder(project), True)
    return Response(status_code=204)


@router.get("/projects/{pid}/download", dependencies=[requires(Perm.PROJECTS)])
async def download_project(pid: int, request: Request) -> Response:
    svc, project = _project(request, pid)
    return _download(await asyncio.to_thread(_zip_dir, svc.src(project), project.name), project.name)


@router.get("/projects/{pid}/source", response_model=Excerpt, dependencies=[requires(Perm.PROJECTS)])
async def source_excerpt(
    pid: int, request: Request, path: str, line: int | None = None, context: int = 6
) -> dict[str, Any]:
    """Lines of one file of the project (around ``line``): what a clicked compiler error shows.
    The path must stay inside the project's source folder; links are not followed."""
    svc, project = _project(request, pid)
    src = svc.src(project).resolve()
    try:
        rel = archive.check_name(path, svc.limits)
    except archive.ArchiveRejected as exc:
        raise XrfError(f"{path}: {exc.message}", 400) from None
    target = src / rel
    try:
        resolved = target.resolve(strict=True)
    except OSError:
        raise NotFound(f"{rel}: no such file in the project") from None
    if not resolved.is_relative_to(src) or target.is_symlink() or not resolved.is_file():
        raise NotFound(f"{rel}: no such file in the project")
    fd = os.open(resolved, os.O_RDONLY | os.O_NOFOLLOW)
    with os.fdopen(fd, "rb") as f:
        data = f.read(SOURCE_MAX_BYTES + 1)
    if len(data) > SOURCE_MAX_BYTES:
        raise TooLarge(f"{rel}: over 1 MB; open it in your editor")
    lines = data.decode("utf-8", "replace").splitlines()
    context = max(0, min(context, 200))
    if line is None:
        first, chunk = 1, lines[:2000]
    else:
        first = max(1, line - context)
        chunk = lines[first - 1 : line + context]
    return {"path": rel, "first": first, "lines": chunk, "total": len(lines), "highlight": line}


@router.post("/projects/{pid}/builds", response_model=Build, status_code=201, dependencies=[requires(Perm.PROJECTS)])
async def start_build(pid: int, request: Request) -> dict[str, Any]:
    """Queue a build (one runs at a time). An unchanged source that built before is not built
    again: that build comes back with ``reused: true``."""
    svc, project = _project(request, pid)
    version = await asyncio.to_thread(svc.versions.current, project, _owner_name(_user(request)))
    row, reused = await svc.submit(project, version, _user(request), authmod.client_address(request))
    return svc.build_dict(row, reused)


@router.get("/projects/{pid}/builds", response_model=list_of(Build), dependencies=[requires(Perm.PROJECTS)])
async def list_builds(pid: int, request: Request) -> list[dict[str, Any]]:
    svc, project = _project(request, pid)
    return [svc.build_dict(b) for b in svc.store.builds(project.id)]


@router.get("/projects/{pid}/builds/{bid}", response_model=Build, dependencies=[requires(Perm.PROJECTS)])
async def get_build(pid: int, bid: int, request: Request) -> dict[str, Any]:
    svc, _, b = _build(request, pid, bid)
    return svc.build_dict(b)


@router.get(
    "/projects/{pid}/builds/{bid}/log", response_class=PlainTextResponse, dependencies=[requires(Perm.PROJECTS)]
)
async def build_log(pid: int, bid: int, request: Request) -> str:
    _, _, b = _build(request, pid, bid)
    if not b.log_path or not Path(b.log_path).exists():
        return ""
    return await asyncio.to_thread(Path(b.log_path).read_text, errors="replace")


@router.post("/projects/{pid}/builds/{bid}/run", status_code=201, dependencies=[requires(Perm.DRIVE)])
async def run_build(pid: int, bid: int, body: RunBuild, request: Request) -> dict[str, Any]:
    """Start a successful build on the bench; the run record names the build
    (``project-<pid>-build-<bid>``) and is linked to it."""
    svc, project, b = _build(request, pid, bid)
    if b.status != "ok" or not b.executable or not Path(b.executable).exists():
        raise Conflict(f"build {bid} is {b.status}; only a successful build can run")
    name = f"project-{pid}-build-{bid}"
    svc.supervisor.catalog.add_external(name, svc.src(project), Path(b.executable), body.sim or svc.settings.sim)
    # The one start-a-run service (server/runs/start.py), as POST /api/runs: the same lease
    # bookkeeping and timing option. The run is the project owner's, whoever starts it. Its
    # refusals (SupervisorError, an xrflab.errors kind) answer through the one handler.
    row = await run_start.start_run(
        request,
        _user(request),
        run_start.RunRequest(name, body.sim, body.max_cycles, body.log_timing),
        owner=project.owner,
        audit_detail={"project": pid, "build": b.id},
    )
    svc.store.link_run(row.id, b)
    return {"run": row.as_dict(), "build_id": b.id, "project_id": pid}
