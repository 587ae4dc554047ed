"""Runs and their logs: the run list with logging figures, downloads in every format (`.rrd`
for the rerun viewer among them), and `read_run_log()` for other parts of the appliance (the 3D view
replays a finished run from it).

Downloads: `raw` is the file itself (streamed); `csv` streams (`iter_csv_chunks`, iterated
in Starlette's thread pool, memory bounded by one chunk); `mat`, `parquet` and `rrd` are
converted once, off the event loop, into `<data>/log-cache/<run>/` (keyed by the source's name,
size and mtime, so a file that grew is converted again) and then served as files. Every output
is what `xrf decode` writes for the same file: the same code (`xrflab.logs.convert`).

A run folder's contents are the loop's to make (its log files in nested folders, like
``home/x/logs/log_…xrf``, but also symlinks or FIFOs if it wants): files are listed without
following symlinks and opened with ``O_NOFOLLOW`` from the run folder down
(``logs/runfolder.py``), so no name in a run folder reads anything outside it, and conversions
are written outside the run folder, where the loop cannot plant a symlink for them to follow.

The rerun viewer (live and recorded) and its live stream are in routes_rerun.py.
"""

from __future__ import annotations

import asyncio
import os
import re
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal

import numpy as np
from fastapi import APIRouter, HTTPException, Query, Request
from fastapi.responses import FileResponse, Response, StreamingResponse
from pydantic import BaseModel, Field

from ..logs.logformat import MAGIC
from ..logs.runfolder import RunPathError, fd_path, open_in, walk_files
from . import ownership
from .auth import Perm, requires
from .runs import record_model

router = APIRouter()

LOG_SUFFIXES = (".xrf", ".bin")
CACHE_DIR = ".cache"  # where conversions once lived in the run folder: never listed
CACHE_ROOT = "log-cache"  # <data>/log-cache/<run id>/: conversions, out of the loop's reach
NOT_LOGS = ("output.txt", "timing.jsonl", "ros-bridge.txt")
MEDIA = {
    "raw": "application/octet-stream",
    "csv": "text/csv; charset=utf-8",
    "mat": "application/x-matlab-data",
    "parquet": "application/vnd.apache.parquet",
    "rrd": "application/octet-stream",
}
_convert_locks: dict[str, asyncio.Lock] = {}


# ---- finding a run's logs (also for other modules) ------------------------------------------


def _is_log(root: Path, rel: str) -> bool:
    """xrflog by its magic; an XRF2 .bin by its two header lines (names, type codes)."""
    path = Path(rel)
    try:
        with open(open_in(root, rel), "rb") as f:
            head = f.read(64 * 1024)
    except (OSError, RunPathError):
        return False
    if head.startswith(MAGIC):
        return True
    if path.suffix != ".bin":
        return False
    lines = head.split(b"\n", 2)
    return (
        len(lines) == 3
        and bool(lines[0])
        and bool(lines[1])
        and re.fullmatch(rb"[0-9 ,\r]+", lines[1]) is not None
        and b"\0" not in lines[0]
    )


def run_log_files(run_dir: str | Path) -> list[Path]:
    """The log files of a run folder (xrflog by content, XRF2 .bin by name), oldest first;
    conversions (.cache/) and the loop's output are not logs."""
    root = Path(run_dir)
    if not root.is_dir():
        return []
    found = []
    # Nested folders too (an XRF2 name like /home/x/logs/log lands in <run>/home/x/logs/);
    # symlinks are not followed: the loop made this folder.
    for rel, st in walk_files(root, skip_top=(CACHE_DIR, "viz", *NOT_LOGS)):
        if _is_log(root, rel):
            found.append((st.st_mtime_ns, rel))
    return [root / rel for _, rel in sorted(found)]


def open_run_log(root: Path, path: Path) -> Any:
    """`open_log` of a run's file, opened without following symlinks (runfolder.open_in); the
    LogFile keeps the file's own path (names in conversions, messages)."""
    from ..logs import LogFormatError, open_log

    rel = path.relative_to(root).as_posix()
    fd = open_in(root, rel)
    try:
        log = open_log(fd_path(fd))  # mapped: stays valid after the fd is closed
    except LogFormatError as exc:
        raise LogFormatError(str(exc).replace(fd_path(fd), str(path))) from None
    finally:
        os.close(fd)
    log.path = path
    return log


def read_run_log(run_dir: str | Path, name: str | None = None) -> dict[str, np.ndarray]:
    """A run's log as NumPy arrays: {column: 1-D array} with `seq`, `cycle`, `t_ns` (xrflog) and
    one array per logged variable (char as uint8), plus `t` (seconds since the first record,
    float64) when the file has a clock. `name`: a file name relative to the run folder (default:
    the newest log). Raises FileNotFoundError when the run has no log; damaged files give every
    complete record (see docs/logging/decoding.md). Blocking: call it off the event loop."""
    from ..logs.convert import _plain

    files = run_log_files(run_dir)
    if name is not None:
        files = [p for p in files if p.relative_to(run_dir).as_posix() == name]
    if not files:
        raise FileNotFoundError(f"{run_dir}: no log file" + (f" named {name!r}" if name else ""))
    log = open_run_log(Path(run_dir), files[-1])
    rec = log.records
    out = {col: np.array(_plain(rec[col])) for col in log.columns if col in rec.dtype.names}
    if log.kind == "xrf2":
        out["seq"] = np.arange(len(rec), dtype=np.uint64)
    if "t_ns" in out and len(out["t_ns"]):
        out["t"] = (out["t_ns"] - out["t_ns"][0]) / 1e9
    return out


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


def _row(request: Request, run_id: int) -> Any:
    """The run if the requester may read it; someone else's answers as a missing one (404)."""
    return ownership.run_or_404(request, run_id)


def _file(row: Any, name: str) -> Path:
    """A log of the run by its relative name; only names the listing would give are accepted."""
    root = Path(row.run_dir)
    for p in run_log_files(root):
        if p.relative_to(root).as_posix() == name:
            return p
    raise HTTPException(404, f"run {row.id} has no log file {name!r}")


def _file_info(root: Path, path: Path) -> dict[str, Any]:
    from ..logs import LogFormatError

    base = {"name": path.relative_to(root).as_posix(), "size": path.lstat().st_size}
    try:
        log = open_run_log(root, path)
    except (OSError, LogFormatError, RunPathError) as exc:
        return base | {
            "kind": "unreadable",
            "records": 0,
            "lost": 0,
            "segments": 0,
            "variables": [],
            "skipped": [],
            "skipped_bytes": 0,
            "error": str(exc),
        }
    return base | {
        "kind": log.kind,
        "records": len(log),
        "lost": log.lost,
        "segments": len(log.segments),
        "variables": [{"name": v.name, "column": v.field, "type": v.type_name} for v in log.variables],
        "skipped": list(log.skipped),
        "skipped_bytes": log.skipped_bytes,
    }


def _download_name(row: Any, path: Path, fmt: str) -> str:
    stem = re.sub(r"[^A-Za-z0-9._-]", "_", path.stem) or "log"
    suffix = path.suffix if fmt == "raw" else "." + fmt
    return f"run{row.id}_{stem}{suffix}"


def _cache_dir(request: Request, row: Any) -> Path:
    settings = getattr(request.app.state, "settings", None)
    data = settings.data_dir if settings is not None else Path(row.run_dir).parent.parent
    return Path(data) / CACHE_ROOT / str(row.id)


async def _cached(path: Path, root: Path, fmt: str, cache: Path) -> Path:
    from ..logs import convert

    rel = path.relative_to(root).as_posix()
    st = await asyncio.to_thread(_stat_in, root, rel)
    key = re.sub(r"[^A-Za-z0-9._-]", "_", rel)
    target = cache / f"{key}.{st.st_size}-{st.st_mtime_ns}.{fmt}"
    lock = _convert_locks.setdefault(str(target), asyncio.Lock())
    async with lock:
        if not target.exists():
            cache.mkdir(parents=True, exist_ok=True, mode=0o700)
            for old in cache.glob(f"{key}.*.{fmt}"):  # superseded conversions of a grown file
                old.unlink(missing_ok=True)
            log = await asyncio.to_thread(open_run_log, root, path)
            await asyncio.to_thread(convert, path, fmt, target, log=log)
    return target


def _stat_in(root: Path, rel: str) -> os.stat_result:
    fd = open_in(root, rel)
    try:
        return os.fstat(fd)
    finally:
        os.close(fd)


def _raw_chunks(fd: int, size: int) -> Iterator[bytes]:
    with open(fd, "rb") as f:  # closed when the response ends, or is dropped
        while size > 0:
            chunk = f.read(min(size, 1 << 20))
            if not chunk:
                return
            size -= len(chunk)
            yield chunk


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
    root = Path(row.run_dir)

    def work() -> list[dict[str, Any]]:
        return [_file_info(root, p) for p in run_log_files(root)]

    files = await asyncio.to_thread(work)
    return {"run": _record(_sup(request), row), "files": files, "timing": (root / "timing.jsonl").is_file()}


@router.get(
    "/api/logs/runs/{run_id}/files/{name:path}",
    dependencies=[requires(Perm.WATCH)],
    summary="download a log: raw, csv (streamed), mat, parquet or rrd",
    response_class=Response,
)
async def download(
    run_id: int, name: str, request: Request, fmt: Literal["raw", "csv", "mat", "parquet", "rrd"] = "raw"
) -> Response:
    from ..logs import LogFormatError, iter_csv_chunks

    row = _row(request, run_id)
    path = _file(row, name)
    root = Path(row.run_dir)
    headers = {"Content-Disposition": f'attachment; filename="{_download_name(row, path, fmt)}"'}
    try:
        if fmt == "raw":
            # Read through a descriptor opened without following symlinks, not by name: the
            # loop may swap the file for a symlink after the listing.
            fd = open_in(root, path.relative_to(root).as_posix())
            size = os.fstat(fd).st_size
            headers["Content-Length"] = str(size)
            return StreamingResponse(_raw_chunks(fd, size), media_type=MEDIA["raw"], headers=headers)
        if fmt == "csv":
            log = await asyncio.to_thread(open_run_log, root, path)
            log.check_uniform()
            headers["X-Log-Skipped"] = str(len(log.skipped))
            headers["X-Log-Lost"] = str(log.lost)
            return StreamingResponse(iter_csv_chunks(path, log=log), media_type=MEDIA["csv"], headers=headers)
        target = await _cached(path, root, fmt, _cache_dir(request, row))
    except LogFormatError as exc:
        raise HTTPException(422, str(exc)) from None
    except (OSError, RunPathError):
        raise HTTPException(404, f"run {row.id} has no log file {name!r}") from None
    return FileResponse(target, media_type=MEDIA[fmt], headers=headers)


@router.get(
    "/api/logs/runs/{run_id}/timing",
    dependencies=[requires(Perm.WATCH)],
    summary="per-second framework timing of the run (JSON lines)",
    response_class=Response,
)
async def timing(run_id: int, request: Request) -> Response:
    row = _row(request, run_id)
    path = Path(row.run_dir) / "timing.jsonl"
    if not path.is_file():
        raise HTTPException(404, f"run {run_id} has no timing series")
    return FileResponse(
        path,
        media_type="application/x-ndjson",
        headers={"Content-Disposition": f'attachment; filename="run{run_id}_timing.jsonl"'},
    )
