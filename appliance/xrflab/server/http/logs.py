"""Runs and their logs: the run list with logging figures and downloads in every format (`.rrd`
for the rerun viewer among them). Finding and opening a run's logs (also for the room and the 3D
view: `read_run_log()`) is xrflab/logs/runlogs.py's.

Downloads: `raw` is the file itself (streamed); `csv` streams from a child process that writes
it (logs/convert_child.py `csv_in_child`: Arrow's libraries stay out of the appliance; read in
Starlette's thread pool, memory bounded by one chunk); `mat`, `parquet` and `rrd` are
converted once, in a child process (logs/convert_child.py: what a conversion allocates leaves
with it), into `<data>/log-cache/<run>/` (keyed by the source's name,
size and mtime, so a file that grew is converted again) and then served as files. Every output
is what `xrf decode` writes for the same file: the same code (`xrflab.logs.convert`).

Each download carries the run's parameter changes (live tuning; the appliance's own log,
params/service.py): a run with changes downloads as CSV in a zip (the samples' CSV and the
change table's; `run<id>_<log>.zip`), MAT/Parquet/.rrd with the table inside
(docs/logging/decoding.md). The conversion cache's key includes a digest of the table, so a set
applied after a download is in the next one.

A run folder's contents are the loop's to make (its log files in nested folders, like
``home/x/logs/log_…xrf``, but also symlinks, FIFOs, hard links or names that are not UTF-8 if it
wants): every listing, open and stat here goes through ``runfolder.py`` (openat2 with
RESOLVE_BENEATH | RESOLVE_NO_SYMLINKS from the run folder's descriptor, plain files only), files
are served from the descriptor that was checked, never by name, a file is mapped only when the
loop cannot truncate it, names are shown escaped (``runfolder.shown``: ``bad\\xff.bin``) and
taken back exactly, and conversions are written outside the run folder, where the loop cannot
plant a symlink for them to follow.

The rerun viewer (live and recorded) and its live stream are in server/http/rerun.py.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import os
import re
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path, PurePosixPath
from typing import Any, BinaryIO, Literal
from urllib.parse import quote

from fastapi import APIRouter, Query, Request
from fastapi.responses import FileResponse, Response, StreamingResponse
from pydantic import BaseModel, Field
from starlette.background import BackgroundTask

from ...errors import Invalid, NotFound, Unavailable
from ...logs.convert_child import ConversionFailed
from ...logs.runlogs import log_files, open_run_log, run_log_files
from ...logs.timing_series import TIMING_FILE
from ...runfolder import RunFolder, RunPathError, shown, unshown
from ..runs.store import record_model
from ..security import ownership
from ..security.auth import Perm, requires

router = APIRouter()

CACHE_ROOT = "log-cache"  # <data>/log-cache/<run id>/: conversions, out of the loop's reach
MEDIA = {
    "raw": "application/octet-stream",
    "csv": "text/csv; charset=utf-8",
    "mat": "application/x-matlab-data",
    "parquet": "application/vnd.apache.parquet",
    "rrd": "application/octet-stream",
}
_convert_locks: dict[str, asyncio.Lock] = {}

# A download's conversion waits in a thread for the heavy-child turn (up to HEAVY_WAIT_S) and then
# for its child. In asyncio's default executor (min(32, cores + 4) threads: 6 on a 2-core VM, 8
# on a Pi 4) a class downloading at once would hold every thread and stall all else the appliance
# does off the event loop (a run's end, uploads, the editor's saves). Downloads get a pool of
# their own: the ones beyond it wait in its queue, without a thread.
DOWNLOAD_THREADS = 4
_downloads = ThreadPoolExecutor(max_workers=DOWNLOAD_THREADS, thread_name_prefix="xrf-download")


async def _in_download_pool(fn: Callable[..., Any], *args: Any) -> Any:
    return await asyncio.get_running_loop().run_in_executor(_downloads, fn, *args)


# ---- models ---------------------------------------------------------------------------------


# The run record as the log listing shows it: runs.RunRow's fields (one definition), without
# where the run lived (shm, pid, run folder) and its exit status, plus its duration and liveness.
RunLogRecord = record_model(
    "RunLogRecord",
    exclude=frozenset({"shm", "pid", "exit_code", "exit_signal", "run_dir"}),
    duration_s=(float | None, Field(description="ended (or now, while live) - started")),
    live=(bool, Field(description="the run is active; counts are the loop's, live")),
)


class LogFileInfo(BaseModel):
    name: str = Field(description="path relative to the run folder; use it in download URLs")
    size: int
    kind: str = Field(description="xrflog | xrf2 | unreadable")
    records: int
    lost: int
    segments: int
    variables: list[dict[str, str]]
    skipped: list[str] = Field(description="what the decoder could not use (damage, truncation)")
    skipped_bytes: int
    error: str = ""


class RunLogs(BaseModel):
    run: RunLogRecord  # type: ignore[valid-type]  # a model made by runs.record_model
    files: list[LogFileInfo]
    timing: bool = Field(description="timing.jsonl (per-second stage timing) exists")


# ---- helpers --------------------------------------------------------------------------------


def _sup(request: Request) -> Any:
    return request.app.state.supervisor


def _record(sup: Any, row: Any) -> dict[str, Any]:
    d = row.as_dict()
    run = sup.current
    live = bool(run is not None and run.row.id == row.id and run.alive and not run.ended.is_set())
    if live and run.last_status is not None:
        s = run.last_status
        d.update(cycles=s.cycles, misses=s.missed, log_lost=s.log_lost)
        rl = run.logging
        d["log_records"] = rl.writer.stats.records if rl is not None else s.log_written
    end = d["ended"] if d["ended"] is not None else (time.time() if live else None)
    d["duration_s"] = round(end - d["started"], 3) if end is not None else None
    d["live"] = live
    return d


async def _drain_live(request: Request, row: Any, timing: bool = False) -> None:
    """A log of the running run is downloaded: its host writer drains first, so the file has
    every record the loop logged until now (it drains every few seconds otherwise, nobody
    reading: logs/host_writer.py MAX_PERIOD_S); `timing`: the timing series' lines taken so
    far are written first (they are written at the drains)."""
    run = _sup(request).current
    rl = run.logging if run is not None and run.row.id == row.id and not run.ended.is_set() else None
    if rl is not None:
        await asyncio.to_thread(rl.writer.flush_timing if timing else rl.writer.drain)


def _row(request: Request, run_id: int) -> Any:
    """The run if the requester may read it; someone else's answers as a missing one (404)."""
    return ownership.run_or_404(request, run_id)


def _file(row: Any, name: str) -> str:
    """A log of the run by the name the listing shows; only names the listing would give are
    accepted. Returns the name relative to the run folder (as the file system has it). Blocking."""
    rel = unshown(name)
    if rel not in run_log_files(row.run_dir):
        raise NotFound(f"run {row.id} has no log file {name!r}")
    return rel


def _text(message: str) -> str:
    """A message that may hold a file system name: no lone surrogate reaches JSON."""
    return message.encode("utf-8", "backslashreplace").decode("utf-8")


def _file_info(rf: RunFolder, rel: str, st: os.stat_result) -> dict[str, Any]:
    from ...logs import LogFormatError

    base = {"name": shown(rel), "size": st.st_size}
    try:
        log = open_run_log(rf, rel)
    except (OSError, LogFormatError, RunPathError) as exc:
        return base | {
            "kind": "unreadable",
            "records": 0,
            "lost": 0,
            "segments": 0,
            "variables": [],
            "skipped": [],
            "skipped_bytes": 0,
            "error": _text(str(exc)),
        }
    return base | {
        "size": log.size,
        "kind": log.kind,
        "records": len(log),
        "lost": log.lost,
        "segments": len(log.segments),
        "variables": [{"name": _text(v.name), "column": v.field, "type": v.type_name} for v in log.variables],
        "skipped": [_text(x) for x in log.skipped],
        "skipped_bytes": log.skipped_bytes,
    }


def _download_name(row: Any, rel: str, fmt: str) -> str:
    path = PurePosixPath(rel)
    stem = re.sub(r"[^A-Za-z0-9._-]", "_", path.stem) or "log"
    suffix = re.sub(r"[^A-Za-z0-9._-]", "_", path.suffix) if fmt == "raw" else "." + fmt
    return f"run{row.id}_{stem}{suffix}"


def _cache_dir(request: Request, row: Any) -> Path:
    settings = getattr(request.app.state, "settings", None)
    data = settings.data_dir if settings is not None else Path(row.run_dir).parent.parent
    return Path(data) / CACHE_ROOT / str(row.id)


def _open_file(run_dir: str | Path, rel: str) -> tuple[int, os.stat_result]:
    """`rel` opened through the run folder's helper, with its fstat (what is served is what was
    checked: the descriptor, not the name)."""
    with RunFolder(run_dir) as rf:
        fd = rf.open(rel)
    return fd, os.fstat(fd)


def _changes(request: Request, run_id: int) -> list[dict[str, Any]]:
    """The run's parameter change table ([] when none, or an app without live tuning)."""
    svc = getattr(request.app.state, "params", None)
    return svc.changes(run_id) if svc is not None else []


def _convert_in_child(run_dir: str | Path, rel: str, fmt: str, target: Path, changes: list[dict[str, Any]]) -> None:
    """The conversion in a process of its own (logs/convert_child.py: the rerun SDK keeps every
    recording made in this process, and a large conversion's peak would stay here), handed the
    file as RunFolder opens it."""
    from ...logs.convert_child import convert_in_child

    with RunFolder(run_dir) as rf:
        fd = rf.open_mappable(rel)
        name = rf.path / shown(rel)
    try:
        convert_in_child(fd, name, fmt, target, changes or None)
    finally:
        os.close(fd)


def _csv_in_child(
    run_dir: str | Path, rel: str, changes: list[dict[str, Any]], names: tuple[str, str]
) -> tuple[dict[str, int], Iterator[bytes]]:
    """The CSV written by a child process (logs/convert_child.py: Arrow writes it, and its
    libraries are not loaded into the appliance), handed the file as RunFolder opens it."""
    from ...logs.convert_child import csv_in_child

    with RunFolder(run_dir) as rf:
        fd = rf.open_mappable(rel)
        name = rf.path / shown(rel)
    try:
        return csv_in_child(fd, name, changes or None, names)
    finally:
        os.close(fd)


async def _cached(run_dir: str | Path, rel: str, fmt: str, cache: Path, changes: list[dict[str, Any]]) -> Path:
    fd, st = await asyncio.to_thread(_open_file, run_dir, rel)
    os.close(fd)
    # One cache name per file: its name made safe, plus a digest of the real name (two names
    # that differ only where they are not plain ASCII do not share a conversion).
    digest = hashlib.sha256(os.fsencode(rel)).hexdigest()[:10]
    key = re.sub(r"[^A-Za-z0-9._-]", "_", rel)[:100] + "-" + digest
    tuned = hashlib.sha256(json.dumps(changes).encode()).hexdigest()[:10] if changes else "0"
    target = cache / f"{key}.{st.st_size}-{st.st_mtime_ns}-{tuned}.{fmt}"
    lock = _convert_locks.setdefault(str(target), asyncio.Lock())
    async with lock:
        if not target.exists():
            cache.mkdir(parents=True, exist_ok=True, mode=0o700)
            for old in cache.glob(f"{key}.*.{fmt}"):  # superseded conversions of a grown file
                old.unlink(missing_ok=True)
            # An untuned run's download is byte for byte what `xrf decode` writes (no empty table).
            await _in_download_pool(_convert_in_child, run_dir, rel, fmt, target, changes)
    return target


def _raw_chunks(f: BinaryIO, size: int) -> Iterator[bytes]:
    with f:  # closed when the response ends (or by its background task, if never started)
        while size > 0:
            chunk = f.read(min(size, 1 << 20))
            if not chunk:
                return
            size -= len(chunk)
            yield chunk


def _stream(fd: int, size: int, media: str, headers: dict[str, str]) -> StreamingResponse:
    """The open file `fd` (its first `size` bytes) as the response body."""
    f = open(fd, "rb")
    headers["Content-Length"] = str(size)
    return StreamingResponse(
        _raw_chunks(f, size), media_type=media, headers=headers, background=BackgroundTask(f.close)
    )


# ---- runs and files -------------------------------------------------------------------------


@router.get(
    "/api/logs/runs",
    response_model=list[RunLogRecord],  # type: ignore[valid-type]  # a model made at import (runs.record_model)
    dependencies=[requires(Perm.WATCH)],
    summary="runs with their logging figures (newest first)",
)
async def list_runs(request: Request, limit: int = Query(100, ge=1, le=10000)) -> list[dict[str, Any]]:
    sup = _sup(request)
    return [_record(sup, r) for r in ownership.runs(request, limit)]  # the requester's (educators: all)


@router.get(
    "/api/logs/runs/{run_id}",
    response_model=RunLogs,
    dependencies=[requires(Perm.WATCH)],
    summary="one run and its log files, with what the decoder skipped",
)
async def run_logs(run_id: int, request: Request) -> dict[str, Any]:
    row = _row(request, run_id)

    def work() -> tuple[list[dict[str, Any]], bool]:
        try:
            rf = RunFolder(row.run_dir)
        except OSError:
            return [], False
        with rf:
            return [_file_info(rf, rel, st) for rel, st in log_files(rf)], rf.is_file(TIMING_FILE)

    files, has_timing = await asyncio.to_thread(work)
    return {"run": _record(_sup(request), row), "files": files, "timing": has_timing}


@router.get(
    "/api/logs/runs/{run_id}/files/{name:path}",
    dependencies=[requires(Perm.WATCH)],
    summary="download a log: raw, csv (streamed), mat, parquet or rrd",
    response_class=Response,
)
async def download(
    run_id: int, name: str, request: Request, fmt: Literal["raw", "csv", "mat", "parquet", "rrd"] = "raw"
) -> Response:
    from ...logs import LogFormatError
    from ...logs.convert import csv_zip_names

    row = _row(request, run_id)
    rel = await asyncio.to_thread(_file, row, name)
    await _drain_live(request, row)
    headers = {"Content-Disposition": f'attachment; filename="{_download_name(row, rel, fmt)}"'}
    changes = await asyncio.to_thread(_changes, request, row.id) if fmt != "raw" else []
    try:
        if fmt == "raw":
            # Read through the descriptor that was checked, not by name: the loop may swap the
            # file for a symlink after the listing.
            fd, st = await asyncio.to_thread(_open_file, row.run_dir, rel)
            return _stream(fd, st.st_size, MEDIA["raw"], headers)
        if fmt == "csv":
            zipped = _download_name(row, rel, "zip")
            names = csv_zip_names(PurePosixPath(zipped).stem, row.id)
            counts, chunks = await _in_download_pool(_csv_in_child, row.run_dir, rel, changes, names)
            headers["X-Log-Skipped"] = str(counts["skipped"])
            headers["X-Log-Lost"] = str(counts["lost"])
            headers["X-Param-Changes"] = str(len(changes))
            if changes:  # the samples' CSV and the change table's, as one zip
                headers["Content-Disposition"] = f'attachment; filename="{zipped}"'
                return StreamingResponse(chunks, media_type="application/zip", headers=headers)
            return StreamingResponse(chunks, media_type=MEDIA["csv"], headers=headers)
        target = await _cached(row.run_dir, rel, fmt, _cache_dir(request, row), changes)
    except LogFormatError as exc:
        raise Invalid(_text(str(exc))) from None
    except (OSError, RunPathError):
        raise NotFound(f"run {row.id} has no log file {name!r}") from None
    except ConversionFailed as exc:  # the child's own failure (a full disk, say): said, not a 500
        raise Unavailable(_text(str(exc))) from None
    return FileResponse(target, media_type=MEDIA[fmt], headers=headers)


# rerun's web viewer (0.41) opens an http(s) URL only when its path ends in a file extension it
# knows (given `…/files/<log>?fmt=rrd` it said "Failed to parse URL") and fetches it without the
# session cookie (a 401): either left "Open in rerun" with an empty viewer. So the page asks for a
# link to the one log: a path ending in .rrd that carries its own credential (accounts.new_link:
# this user, this run's log, for VIEWER_LINK_TTL_S), handed to the viewer (frontend/pages/runs.js,
# rerun-tab.js). The download behind it is the same, with the same checks, as that user.
VIEWER_LINK_TTL_S = 3600.0


def _viewer_scope(run_id: int, name: str) -> str:
    return f"rrd|{run_id}|{name}"


@router.get(
    "/api/logs/runs/{run_id}/viewer-link/{name:path}",
    dependencies=[requires(Perm.WATCH)],
    summary="a link to a log as .rrd that rerun's web viewer can open (its own credential, for an hour)",
)
async def viewer_link(run_id: int, name: str, request: Request) -> dict[str, Any]:
    row = _row(request, run_id)
    await asyncio.to_thread(_file, row, name)  # a log of the run, or the same 404 as a download
    accounts = request.app.state.security.accounts
    link = accounts.new_link(ownership.user_of(request), _viewer_scope(row.id, name), VIEWER_LINK_TTL_S)
    return {"path": f"/api/logs/viewer/{link}/{row.id}/{quote(name)}.rrd", "expires_s": VIEWER_LINK_TTL_S}


@router.api_route(
    "/api/logs/viewer/{link}/{run_id}/{name:path}",
    methods=["GET", "HEAD"],  # the viewer may ask HEAD first
    # Public as a route: the link in the path is the credential (checked below, before anything).
    dependencies=[requires(Perm.PUBLIC)],
    summary="a log as .rrd through a viewer link (viewer-link)",
    response_class=Response,
)
async def viewer_rrd(link: str, run_id: int, name: str, request: Request) -> Response:
    name = name.removesuffix(".rrd") if name.endswith(".rrd") else ""
    if not name or request.app.state.security.resolve_link(request, link, _viewer_scope(run_id, name)) is None:
        raise NotFound(f"run {run_id} has no log file {name!r}")  # a wrong or old link: as if missing
    return await download(run_id, name, request, "rrd")


@router.get(
    "/api/logs/runs/{run_id}/timing",
    dependencies=[requires(Perm.WATCH)],
    summary="per-second framework timing of the run (JSON lines)",
    response_class=Response,
)
async def timing(run_id: int, request: Request) -> Response:
    row = _row(request, run_id)
    await _drain_live(request, row, timing=True)
    try:
        fd, st = await asyncio.to_thread(_open_file, row.run_dir, TIMING_FILE)
    except (OSError, RunPathError):  # none, or not a plain file of the run (a link, a FIFO, ...)
        raise NotFound(f"run {run_id} has no timing series") from None
    headers = {"Content-Disposition": f'attachment; filename="run{run_id}_timing.jsonl"'}
    return _stream(fd, st.st_size, "application/x-ndjson", headers)
