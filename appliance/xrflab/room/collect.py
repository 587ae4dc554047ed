"""Collecting an assignment's runs from every bench as one archive (issue 21).

1. The room (``Collection``) sends ``collect`` (collection id, assignment id, formats) to every
   enrolled bench. Benches offline then are ``missing`` at once; the others have until the
   deadline.
2. A bench (``pack_bench``) finds the projects made from that assignment (origin
   ``assignment:<id>``, whoever owns them), their runs (``project_runs``) and packs, per run,
   ``<student>/<run id>/run.json`` (the run record), ``output.txt`` (the loop's output) and every
   log file as the student's loop wrote it (xrflog or an XRF2 ``.bin``: the format they chose in
   their controller) plus the conversions the educator asked for (csv, mat, parquet: the code of
   the appliance's log downloads, ``logs/convert.py``). A ``bench.json`` lists what is in it and
   what did not fit. It uploads the .tar.gz to the room (``POST
   /api/room/collections/<id>/benches/<name>``) with a token signed with its enrolment key (use
   ``collect``).
3. The room (``assemble``) makes one zip laid out ``<student>/<bench>/<run id>/...`` with
   ``manifest.json``: every bench with its status (collected, missing, failed, no answer) and every
   run collected. Names from a bench are checked (one safe path component each, regular files
   only), and sizes are bounded: ``BENCH_MAX`` per bench, ``TOTAL_MAX`` per collection (what did
   not fit is listed in the manifest, never silently left out).
"""

from __future__ import annotations

import functools
import io
import json
import os
import re
import tarfile
import tempfile
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

BENCH_MAX = 256 << 20  # bytes of one bench's upload
TOTAL_MAX = 1 << 30  # bytes of files in one collection's archive
OUTPUT_MAX = 1 << 20  # output.txt is the loop's printout: its first MB
FORMATS = ("csv", "mat", "parquet")
SAFE = re.compile(r"^[A-Za-z0-9_.+@-][A-Za-z0-9_.+@ -]{0,127}$")


def safe_part(name: str) -> str:
    """One path component of the archive from a name a student or bench chose."""
    out = re.sub(r"[^A-Za-z0-9_.+@-]", "_", name or "")[:128].lstrip(".")
    return out or "_"


# ---- the bench ----------------------------------------------------------------------------------


@dataclass
class RunToPack:
    student: str
    project: dict[str, Any]
    build_id: int
    record: dict[str, Any]
    run_dir: str


def pack_bench(
    bench: str, aid: str, runs: list[RunToPack], formats: list[str], out: Path, limit: int = BENCH_MAX
) -> dict[str, Any]:
    """Write the bench's .tar.gz of `runs` to `out`; returns bench.json (also inside). Blocking."""
    from ..logs.convert import convert
    from ..logs.runlogs import log_files, open_run_log
    from ..runfolder import RunFolder, RunPathError

    total = 0
    listed: list[dict[str, Any]] = []
    left_out: list[dict[str, Any]] = []
    with tarfile.open(out, "w:gz") as tar, tempfile.TemporaryDirectory(prefix="xrf-collect-") as tmp:

        def add_bytes(name: str, data: bytes) -> None:
            nonlocal total
            info = tarfile.TarInfo(name)
            info.size, info.mtime, info.mode = len(data), int(time.time()), 0o644
            tar.addfile(info, io.BytesIO(data))
            total += len(data)

        def add_file(name: str, path: Path | None, fd: int | None = None) -> bool:
            nonlocal total
            f = os.fdopen(fd, "rb") if fd is not None else open(path, "rb")  # type: ignore[arg-type]
            with f:
                size = os.fstat(f.fileno()).st_size
                if total + size > limit:
                    left_out.append({"file": name, "bytes": size, "why": f"over the bench's {limit >> 20} MB"})
                    return False
                info = tarfile.TarInfo(name)
                info.size, info.mtime, info.mode = size, int(time.time()), 0o644
                tar.addfile(info, f)
                total += size
            return True

        for r in runs:
            base = f"{safe_part(r.student)}/{int(r.record['id'])}"
            files: list[str] = []
            # The run folder is the loop's: everything in it through its helper (no link
            # followed, plain files only, output.txt read up to OUTPUT_MAX).
            try:
                rf = RunFolder(r.run_dir)
            except OSError as exc:
                left_out.append({"file": f"{base}/", "why": f"no run folder: {exc.strerror}"})
                rf = None
            if rf is not None:
                with rf:
                    for rel, _ in log_files(rf):
                        name = f"{base}/logs/{'/'.join(safe_part(p) for p in rel.split('/'))}"
                        try:  # a copy if the loop could still change it (its size must hold)
                            if add_file(name, None, rf.open_mappable(rel)):
                                files.append(name)
                        except (OSError, RunPathError) as exc:
                            left_out.append({"file": name, "why": str(exc)[:200]})
                            continue
                        for fmt in formats:
                            conv = Path(name).with_suffix("." + fmt).as_posix()
                            target = Path(tmp) / f"c{len(files)}.{fmt}"
                            try:
                                log = open_run_log(rf, rel)
                                convert(log.path, fmt, target, log=log)
                            except Exception as exc:  # an undecodable log still has its raw file above
                                left_out.append({"file": conv, "why": f"not converted: {exc}"[:300]})
                                continue
                            if add_file(conv, target):
                                files.append(conv)
                            target.unlink(missing_ok=True)
                    try:
                        fd = rf.open("output.txt")
                        with os.fdopen(fd, "rb") as f:
                            add_bytes(f"{base}/output.txt", f.read(OUTPUT_MAX))
                        files.append(f"{base}/output.txt")
                    except (OSError, RunPathError):
                        pass
            record = {**r.record, "student": r.student, "bench": bench, "project": r.project, "build_id": r.build_id}
            add_bytes(f"{base}/run.json", json.dumps(record, indent=1, default=str).encode())
            listed.append(
                {
                    "student": r.student,
                    "run_id": int(r.record["id"]),
                    "project": r.project,
                    "files": files + [f"{base}/run.json"],
                }
            )
        manifest = {
            "bench": bench,
            "assignment": aid,
            "formats": formats,
            "runs": listed,
            "left_out": left_out,
            "bytes": total,
        }
        add_bytes("bench.json", json.dumps(manifest, indent=1).encode())
    return manifest


# ---- the room -----------------------------------------------------------------------------------


@dataclass
class Collection:
    id: str
    assignment: dict[str, Any]
    formats: list[str]
    by: str
    folder: Path
    deadline: float
    benches: dict[str, str] = field(default_factory=dict)  # name -> waiting | collected | missing | failed
    errors: dict[str, str] = field(default_factory=dict)
    created: float = field(default_factory=time.time)
    archive: Path | None = None

    @property
    def done(self) -> bool:
        return time.time() >= self.deadline or all(s != "waiting" for s in self.benches.values())

    def view(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "assignment": self.assignment["id"],
            "name": self.assignment["name"],
            "formats": self.formats,
            "benches": dict(self.benches),
            "errors": dict(self.errors),
            "done": self.done,
            "deadline": self.deadline,
            "archive": f"/api/room/collections/{self.id}/archive" if self.done else None,
        }

    def upload_path(self, bench: str) -> Path:
        return self.folder / f"{safe_part(bench)}.tar.gz"


def assemble(c: Collection, out: Path, total_max: int = TOTAL_MAX) -> dict[str, Any]:
    """One zip of every bench's upload, ``<student>/<bench>/<run id>/...`` and manifest.json. Blocking."""
    runs: list[dict[str, Any]] = []
    benches: dict[str, dict[str, Any]] = {}
    left_out: list[dict[str, Any]] = []
    total = 0
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as z:
        for bench, status in sorted(c.benches.items()):
            status = "no answer" if status == "waiting" else status
            entry: dict[str, Any] = {"status": status, "runs": 0}
            if c.errors.get(bench):
                entry["error"] = c.errors[bench]
            benches[bench] = entry
            if status != "collected":
                continue
            try:
                with tarfile.open(c.upload_path(bench), "r:gz") as tar:
                    for m in tar:
                        parts = m.name.split("/")
                        if m.name == "bench.json" and m.isfile() and m.size < (8 << 20):
                            f = tar.extractfile(m)
                            mine = json.loads(f.read()) if f is not None else {}
                            entry["runs"] = len(mine.get("runs", []))
                            entry["bytes"] = mine.get("bytes", 0)
                            for r in mine.get("runs", []):
                                # the bench's names are <student>/<run id>/...; here they gain the bench
                                files = [
                                    "/".join([p[0], safe_part(bench), *p[1:]])
                                    for p in (str(f).split("/") for f in r.get("files", []))
                                    if len(p) >= 3
                                ]
                                runs.append(
                                    {
                                        **r,
                                        "bench": bench,
                                        "files": files,
                                        "folder": f"{safe_part(str(r.get('student')))}/{safe_part(bench)}/"
                                        f"{int(r.get('run_id', 0))}/",
                                    }
                                )
                            left_out += [{**x, "bench": bench} for x in mine.get("left_out", [])]
                            continue
                        if (
                            not m.isfile()
                            or len(parts) < 3
                            or not all(SAFE.match(p) for p in parts)
                            or not parts[1].isdigit()
                        ):
                            left_out.append({"bench": bench, "file": m.name[:300], "why": "not a file of a run"})
                            continue
                        if total + m.size > total_max:
                            left_out.append(
                                {
                                    "bench": bench,
                                    "file": m.name,
                                    "bytes": m.size,
                                    "why": f"over the collection's {total_max >> 20} MB",
                                }
                            )
                            continue
                        f = tar.extractfile(m)
                        if f is None:
                            continue
                        name = "/".join([parts[0], safe_part(bench), *parts[1:]])
                        with z.open(name, "w", force_zip64=True) as dst:
                            for chunk in iter(functools.partial(f.read, 1 << 20), b""):
                                dst.write(chunk)
                        total += m.size
            except (OSError, tarfile.TarError, ValueError) as exc:
                entry.update(status="failed", error=f"unreadable upload: {exc}"[:300])
        manifest = {
            "assignment": c.assignment,
            "collection": c.id,
            "by": c.by,
            "created": c.created,
            "assembled": time.time(),
            "formats": c.formats,
            "layout": "<student>/<bench>/<run id>/",
            "benches": benches,
            "missing": sorted(b for b, e in benches.items() if e["status"] != "collected"),
            "runs": runs,
            "left_out": left_out,
            "bytes": total,
        }
        z.writestr("manifest.json", json.dumps(manifest, indent=1, default=str))
    return manifest
