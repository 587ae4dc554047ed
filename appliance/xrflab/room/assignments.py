"""Publishing an assignment: the room's side (the bench's is projects/assignments.py and bench.py).

The educator picks one of the appliance's templates (``student_projects/templates``: base, 20sim)
or uploads an archive (zip, tar, tar.gz: checked as a student's upload is), and a name. The room
keeps it in ``<room data>/assignments/<id>.tar.gz`` with ``index.json`` and publishes it retained
on ``xrf/assignment/<id>`` (QoS 1): every enrolled bench gets it now, and a bench that was offline
gets it from the broker when it reconnects. The broker keeps no disk (broker.py), so the room
publishes every assignment again whenever it (re)connects.

The message (payloads.Assignment) carries the id, name, who published it, the archive's size and sha256, and either the
archive itself (``inline``, base64, up to ``INLINE_MAX`` bytes) or nothing more: a bench then
fetches ``GET /api/room/assignments/<id>/archive`` from the room over HTTP(S) with a token it
signs with its own enrolment key (sso.mint, use ``assignment``, 60 s, once), so MQTT never carries
megabytes and nobody but an enrolled bench can fetch it.
"""

from __future__ import annotations

import base64
import json
import os
import secrets
import shutil
import tarfile
import tempfile
import time
from pathlib import Path
from typing import Any

from ..projects import archive
from ..projects.assignments import LIMITS
from ..projects.digest import sha256_file
from .payloads import INLINE_MAX, Assignment

SKIP = set(archive.SKIPPED_DIRS)


def template_archive(template_dir: Path, out: Path) -> None:
    """A built-in template folder as a .tar.gz (regular files only, the upload's skipped folders out)."""
    with tarfile.open(out, "w:gz") as t:
        for dirpath, dirnames, filenames in os.walk(template_dir):
            dirnames[:] = sorted(d for d in dirnames if d not in SKIP)
            for f in sorted(filenames):
                p = Path(dirpath) / f
                if p.is_symlink() or not p.is_file():
                    continue
                rel = p.relative_to(template_dir).as_posix()
                info = t.gettarinfo(str(p), arcname=f"{template_dir.name}/{rel}")
                info.uid = info.gid = 0
                info.uname = info.gname = ""
                info.mode = 0o644
                with open(p, "rb") as fh:
                    t.addfile(info, fh)


class RoomAssignments:
    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.index_path = folder / "index.json"
        try:
            self.index: dict[str, dict[str, Any]] = json.loads(self.index_path.read_text())
        except (OSError, ValueError):
            self.index = {}

    def archive_path(self, aid: str) -> Path:
        return self.folder / f"{aid}.tar.gz"

    def _save(self) -> None:
        tmp = self.index_path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.index))
        tmp.replace(self.index_path)

    def add(self, name: str, source: Path, by: str, template: str = "") -> dict[str, Any]:
        """Keep the archive `source` (moved here) as a new assignment. It is checked as a student's
        upload is (archive.check raises ArchiveRejected), so no bench receives what it would refuse."""
        manifest = archive.check(source, LIMITS)
        self.folder.mkdir(parents=True, exist_ok=True)
        aid = f"a{time.strftime('%Y%m%d')}-{secrets.token_hex(4)}"
        dest = self.archive_path(aid)
        shutil.move(str(source), dest)
        meta = {
            "id": aid,
            "name": name,
            "by": by,
            "t": time.time(),
            "template": template,
            "size": dest.stat().st_size,
            "sha256": sha256_file(dest),
            "files": len(manifest.files),
        }
        self.index[aid] = meta
        self._save()
        return meta

    def add_template(self, name: str, template_dir: Path, by: str) -> dict[str, Any]:
        self.folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=self.folder, prefix=".tpl-", suffix=".tar.gz")
        os.close(fd)
        try:
            template_archive(template_dir, Path(tmp))
            return self.add(name, Path(tmp), by, template=template_dir.name)
        finally:
            Path(tmp).unlink(missing_ok=True)

    def message(self, aid: str) -> Assignment:
        """What ``xrf/assignment/<id>`` says."""
        meta = self.index[aid]
        inline = None
        if meta["size"] <= INLINE_MAX:
            inline = base64.b64encode(self.archive_path(aid).read_bytes()).decode()
        return Assignment.make(
            **{k: meta[k] for k in ("id", "name", "by", "t", "template", "size", "sha256", "files")},
            path=f"/api/room/assignments/{aid}/archive",
            inline=inline,
        )

    def list(self) -> list[dict[str, Any]]:
        return sorted(self.index.values(), key=lambda m: m["t"])
