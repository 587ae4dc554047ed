"""Editing a project in the browser: its files, saving (each save a new source version, built at
once), its version history and diffs (between versions, or against a template).

The project routes' rules hold here unchanged (server/http/projects.py): PROJECTS for every route,
someone else's project answers the same 404 as a missing one (server/security/ownership.py), the audit trail
records who changed what. A path must be a plain relative name inside the project (the upload
checker's rule, archive.check_name: no ``..``, no absolute path, no control characters), never
through a link, never in a folder an upload leaves out (``build/``, ``.git/``, ...). Only text
files (UTF-8, no NUL byte) of at most ``FILE_MAX_BYTES`` are read or written; anything else is a
clear 4xx and changes nothing.

A save carries the version the editor's text came from (``base``); if the file changed since in
a newer version (another tab, an upload), the save is refused with 409 and the newer version's
number, so nothing is overwritten unseen and the editor keeps the student's text.
"""

from __future__ import annotations

import asyncio
import os
import secrets
import stat
from pathlib import Path
from typing import Any

from fastapi import APIRouter, Request
from pydantic import BaseModel, Field

from ...errors import Conflict, NotFound, TooLarge, XrfError
from ...projects import archive
from ...projects import versions as versions_mod
from ...projects.service import TEMPLATES, ProjectsService, projects_of
from ...projects.store import ProjectRow, VersionRow
from ...records import list_of
from ..security import audit, ownership
from ..security.auth import Perm, client_address, requires

router = APIRouter(prefix="/api", tags=["editor"])
# Debian's libjs-codemirror (CodeMirror 5); XRF_CODEMIRROR_DIR for another install of it.
CODEMIRROR_DIR = Path(os.environ.get("XRF_CODEMIRROR_DIR", "/usr/share/javascript/codemirror"))
FILE_MAX_BYTES = 1 << 20
SNIFF_BYTES = 8192


# ---- models ---------------------------------------------------------------------------------------


class FileInfo(BaseModel):
    path: str
    size: int
    editable: bool
    reason: str = Field("", description="why a file cannot be edited here (binary, too large)")


class FileList(BaseModel):
    version: int
    files: list[FileInfo]


class FileContent(BaseModel):
    path: str
    version: int
    size: int
    editable: bool
    reason: str = ""
    content: str = Field("", description="the text; empty when not editable")


# A version as served: its one definition, projects/store.py's VersionRow, plus its newest build.
Version = VersionRow.api_model(
    "Version",
    build=(dict[str, Any] | None, Field(None, description="the newest build of this source: id, status, result")),
)


class SaveResult(BaseModel):
    version: Version  # type: ignore[valid-type]  # a model made at import (VersionRow.api_model)
    new_version: bool = Field(description="false: the text was the same as the latest version's")
    build: dict[str, Any] | None = Field(None, description="the build queued (or reused) for this version")


class FileDiff(BaseModel):
    path: str
    status: str
    added: int
    removed: int
    diff: str | None = Field(description="unified diff; null for a binary or oversized file")


class Diff(BaseModel):
    a: str
    b: str
    added: int
    removed: int
    files: list[FileDiff]


# ---- helpers --------------------------------------------------------------------------------------


def _user(request: Request) -> Any:
    return ownership.user_of(request)


def _project(request: Request, pid: int) -> tuple[ProjectsService, ProjectRow]:
    """The projects service and the requester's project `pid` (someone else's: 404, as missing)."""
    svc = projects_of(request)
    return svc, svc.project_for(_user(request), pid)


def _audit(request: Request, action: str, detail: dict[str, Any]) -> None:
    audit.record(_user(request), action, detail, client_address(request))


def _author(request: Request) -> str:
    return str(_user(request).username)


def _checked(path: str, svc: ProjectsService) -> str:
    try:
        rel = archive.check_name(path, svc.limits)
    except archive.ArchiveRejected as exc:
        raise XrfError(f"{path[:200]}: {exc.message}", 400) from None
    if rel.split("/", 1)[0] in archive.SKIPPED_DIRS:
        raise XrfError(
            f"{rel}: {rel.split('/', 1)[0]}/ is left out of projects (builds and tools "
            "write there); put the file elsewhere",
            400,
        )
    return rel


def _why_not_text(data: bytes, complete: bool) -> str:
    """'' for text this editor may show and save; else why not."""
    if b"\0" in data:
        return "not a text file (binary)"
    try:
        data.decode("utf-8")
    except UnicodeDecodeError as exc:
        # A sniffed prefix may end inside a multi-byte character: that is still text.
        if complete or exc.start < len(data) - 3:
            return "not a text file (not UTF-8)"
    return ""


def _file_info(tree: Path, rel: str) -> dict[str, Any]:
    p = tree / rel
    size = p.stat().st_size
    if size > FILE_MAX_BYTES:
        return {"path": rel, "size": size, "editable": False, "reason": f"over {FILE_MAX_BYTES >> 20} MB"}
    with open(p, "rb") as f:
        head = f.read(SNIFF_BYTES)
    why = _why_not_text(head, size <= SNIFF_BYTES)
    return {"path": rel, "size": size, "editable": not why, "reason": why}


def _version_dict(svc: ProjectsService, project: ProjectRow, v: VersionRow) -> dict[str, Any]:
    builds = [b for b in svc.store.builds(project.id, 200) if b.source_hash == v.source_hash]
    b = builds[0] if builds else None
    return {**v.as_dict(), "build": {"id": b.id, "status": b.status, "result": b.result} if b else None}


def _no_link_below(root: Path, rel: str) -> None:
    """No component of ``rel`` under ``root`` may be a link (the written file neither)."""
    p = root
    for part in rel.split("/"):
        p = p / part
        try:
            st = os.lstat(p)
        except FileNotFoundError:
            return
        if stat.S_ISLNK(st.st_mode):
            raise NotFound(f"{rel}: no such file in the project")


async def _body(request: Request, limit: int, rel: str) -> bytes:
    """The request body, refused (413) the moment it passes ``limit``."""
    chunks: list[bytes] = []
    total = 0
    async for chunk in request.stream():
        total += len(chunk)
        if total > limit:
            raise TooLarge(
                f"{rel}: over {limit >> 20} MB; files this large are not edited in the "
                "browser (upload the project instead)"
            )
        chunks.append(chunk)
    return b"".join(chunks)


def _conflict(svc: ProjectsService, project: ProjectRow, current: VersionRow, base: int | None, rel: str) -> None:
    """409 when ``rel`` is not what it was in ``base`` any more (changed by a newer version)."""
    if base is None or base == current.n:
        return
    old = svc.store.version(project.id, base)
    if old is None or old.files.get(rel) != current.files.get(rel):
        raise Conflict(
            f"{rel} changed since version {base} (now version {current.n}): "
            "reload it, or save again to overwrite it with your text",
            detail={
                "error": f"{rel} changed since version {base} (now version {current.n}): "
                "reload it, or save again to overwrite it with your text",
                "current_version": current.n,
            },
        )


def _write_working_copy(src: Path, rel: str, data: bytes | None, limits: archive.Limits, current: VersionRow) -> None:
    """``data`` into ``src/rel`` (None: delete it), atomically: a reader sees the old or the new file."""
    _no_link_below(src, rel)
    target = src / rel
    if data is None:
        if rel not in current.files:
            raise NotFound(f"{rel}: no such file in the project")
        os.unlink(target)
        parent = target.parent
        while parent != src and not any(parent.iterdir()):
            parent.rmdir()
            parent = parent.parent
        return
    if target.is_dir():
        raise Conflict(f"{rel} is a folder")
    if rel not in current.files and len(current.files) + 1 > limits.max_files:
        raise TooLarge(f"the project has {len(current.files)} files, the most a project may have")
    parent = target.parent
    for p in reversed([parent, *parent.parents]):
        if p.is_relative_to(src) and p.exists() and not p.is_dir():
            raise Conflict(f"{p.relative_to(src).as_posix()} is a file, not a folder")
    parent.mkdir(parents=True, exist_ok=True)
    tmp = parent / f".{target.name}.xrf-{secrets.token_hex(4)}"
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o640)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        if target.exists():
            os.chmod(tmp, stat.S_IMODE(target.stat().st_mode))  # keep an executable bit
        os.replace(tmp, target)
    finally:
        if tmp.exists():
            tmp.unlink()


def _change(
    svc: ProjectsService, project: ProjectRow, rel: str, data: bytes | None, base: int | None, author: str
) -> tuple[VersionRow, bool]:
    """Write (or delete) one file of the working copy and record the next version, under the
    project's lock so two saves never mix."""
    src = svc.src(project)
    with svc.versions.lock(project):
        current = svc.versions.record(project, author, "existing source")[0]
        _conflict(svc, project, current, base, rel)
        _write_working_copy(src, rel, data, svc.limits, current)
        version, new = svc.versions.record(project, author, ("edit " if data is not None else "delete ") + rel)
        if new:
            tree = svc.versions.tree(project, version)
            svc.store.update_project(
                project.id, files=len(version.files), bytes=sum((tree / f).stat().st_size for f in version.files)
            )
        return version, new


def _side(svc: ProjectsService, request: Request, project: ProjectRow, which: str) -> tuple[str, dict[str, str], Any]:
    """(label, path -> sha256, reader) of one side of a diff: a version number or template:<name>."""
    if which.startswith("template:"):
        name = which.split(":", 1)[1]
        if name not in TEMPLATES:
            raise XrfError(f"no template {name!r}; have: {', '.join(TEMPLATES)}", 400)
        files, read = versions_mod.template_side(request.app.state.settings.projects_dir / "templates" / name)
        return f"template-{name}", files, read
    try:
        n = int(which)
    except ValueError:
        raise XrfError(f"{which!r}: a version number or template:<name>", 400) from None
    v = svc.store.version(project.id, n)
    if v is None:
        raise NotFound(f"no version {n} of project {project.id}")
    return f"v{n}", v.files, lambda rel: svc.versions.read(project, v, rel)


# ---- routes ---------------------------------------------------------------------------------------


@router.get("/projects/{pid}/files", response_model=FileList, dependencies=[requires(Perm.PROJECTS)])
async def list_files(pid: int, request: Request) -> dict[str, Any]:
    """The files of the project's current version, each with whether the editor can open it."""
    svc, project = _project(request, pid)
    v = await asyncio.to_thread(svc.versions.current, project, _author(request))
    tree = svc.versions.tree(project, v)
    files = await asyncio.to_thread(lambda: [_file_info(tree, rel) for rel in sorted(v.files)])
    return {"version": v.n, "files": files}


@router.get("/projects/{pid}/files/{path:path}", response_model=FileContent, dependencies=[requires(Perm.PROJECTS)])
async def read_file(pid: int, path: str, request: Request, version: int | None = None) -> dict[str, Any]:
    """One file's text, of the current version or of ``version``."""
    svc, project = _project(request, pid)
    rel = _checked(path, svc)
    if version is None:
        v = await asyncio.to_thread(svc.versions.current, project, _author(request))
    else:
        found = svc.store.version(project.id, version)
        if found is None:
            raise NotFound(f"no version {version} of project {pid}")
        v = found
    if rel not in v.files:
        raise NotFound(f"{rel}: no such file in the project")
    data = await asyncio.to_thread(svc.versions.read, project, v, rel)
    assert data is not None
    size = (svc.versions.tree(project, v) / rel).stat().st_size
    if size > FILE_MAX_BYTES:
        return {
            "path": rel,
            "version": v.n,
            "size": size,
            "editable": False,
            "reason": f"over {FILE_MAX_BYTES >> 20} MB",
        }
    why = _why_not_text(data, True)
    return {
        "path": rel,
        "version": v.n,
        "size": size,
        "editable": not why,
        "reason": why,
        "content": "" if why else data.decode("utf-8"),
    }


@router.put("/projects/{pid}/files/{path:path}", response_model=SaveResult, dependencies=[requires(Perm.PROJECTS)])
async def save_file(
    pid: int, path: str, request: Request, base: int | None = None, build: bool = True
) -> dict[str, Any]:
    """Save one file (the request body: its UTF-8 text) as the project's next version, then queue
    its build (``build=false``: do not). ``base``: the version the text was edited from."""
    svc, project = _project(request, pid)
    rel = _checked(path, svc)
    data = await _body(request, FILE_MAX_BYTES, rel)
    why = _why_not_text(data, True)
    if why:
        raise XrfError(f"{rel}: {why}; only text files are saved from the editor", 415)
    version, new = await asyncio.to_thread(_change, svc, project, rel, data, base, _author(request))
    _audit(request, "project.edit", {"project": pid, "path": rel, "version": version.n, "bytes": len(data)})
    out: dict[str, Any] = {"version": _version_dict(svc, project, version), "new_version": new, "build": None}
    if build:
        row, reused = await svc.submit(project, version, _user(request), client_address(request))
        out["build"] = svc.build_dict(row, reused)
        out["version"] = _version_dict(svc, project, version)
    return out


@router.delete("/projects/{pid}/files/{path:path}", response_model=SaveResult, dependencies=[requires(Perm.PROJECTS)])
async def delete_file(pid: int, path: str, request: Request, base: int | None = None) -> dict[str, Any]:
    """Remove one file: the project's next version is without it (earlier versions keep it)."""
    svc, project = _project(request, pid)
    rel = _checked(path, svc)
    version, new = await asyncio.to_thread(_change, svc, project, rel, None, base, _author(request))
    _audit(request, "project.edit", {"project": pid, "path": rel, "version": version.n, "deleted": True})
    return {"version": _version_dict(svc, project, version), "new_version": new, "build": None}


@router.get("/projects/{pid}/versions", response_model=list_of(Version), dependencies=[requires(Perm.PROJECTS)])
async def list_versions(pid: int, request: Request) -> list[dict[str, Any]]:
    """Every version of the project's source, newest first, each with its newest build."""
    svc, project = _project(request, pid)
    await asyncio.to_thread(svc.versions.current, project, _author(request))
    return [_version_dict(svc, project, v) for v in svc.store.versions(project.id)]


@router.get("/projects/{pid}/diff", response_model=Diff, dependencies=[requires(Perm.PROJECTS)])
async def diff_versions(pid: int, request: Request, a: str, b: str = "") -> dict[str, Any]:
    """What changed from ``a`` to ``b`` (each a version number or ``template:base``/``template:20sim``,
    the template as the appliance has it; ``b`` defaults to the current version)."""
    svc, project = _project(request, pid)
    current = await asyncio.to_thread(svc.versions.current, project, _author(request))
    la, fa, ra = _side(svc, request, project, a)
    lb, fb, rb = _side(svc, request, project, b or str(current.n))
    files = await asyncio.to_thread(versions_mod.diff, fa, ra, fb, rb, la, lb)
    return {
        "a": la,
        "b": lb,
        "added": sum(f["added"] for f in files),
        "removed": sum(f["removed"] for f in files),
        "files": files,
    }
