"""Assignments on a bench: project templates an educator published from the room (issue 21).

The room sends an assignment as an archive (xrflab.room.assignments); the bench keeps it in
``<data>/assignments/<id>/``: ``src/`` (the archive unpacked with exactly the checks of a student's
upload, ``archive.unpack``) and ``assignment.json`` (id, name, sha256 of the archive, who
published it, when). Installing is atomic (a folder renamed into place), so a half-received
assignment is never listed.

How students get it (server/http/projects.py): an assignment is one more template (``GET
/api/project-templates`` lists it as ``assignment:<id>``; ``POST /api/projects/from-template``
copies it), and the first time a student lists their projects on this bench after it arrived, a
copy is made for them: a project of their own (origin ``assignment:<id>``) under the ordinary
ownership rule (someone else's copy answers as a missing one). The copy made for a student is
remembered (``ProjectStore.assignment_copies``): a copy the student deleted is not made again.
"""

from __future__ import annotations

import json
import os
import re
import secrets
import shutil
import time
from pathlib import Path
from typing import Any

from . import archive
from .digest import sha256_file

ID_RE = re.compile(r"^[a-z0-9][a-z0-9-]{0,39}$")
ORIGIN_PREFIX = "assignment:"
# An assignment is a starting point, not a data set: smaller than a student's upload may be.
LIMITS = archive.Limits(max_upload=32 << 20, max_total=64 << 20)


def check_id(aid: str) -> str:
    if not isinstance(aid, str) or not ID_RE.match(aid):
        raise ValueError(f"assignment id {aid!r}: 1-40 characters a-z, 0-9 and '-'")
    return aid


def origin(aid: str) -> str:
    return ORIGIN_PREFIX + aid


class Assignments:
    """The assignments this bench has received (``root`` = ``<data>/assignments``)."""

    def __init__(self, root: Path) -> None:
        self.root = root

    def _folder(self, aid: str) -> Path:
        return self.root / check_id(aid)

    def src(self, aid: str) -> Path:
        return self._folder(aid) / "src"

    def get(self, aid: str) -> dict[str, Any] | None:
        try:
            return json.loads((self._folder(aid) / "assignment.json").read_text())
        except (OSError, ValueError):
            return None

    def list(self) -> list[dict[str, Any]]:
        """Oldest first (the order they were published in)."""
        if not self.root.is_dir():
            return []
        out = [m for d in self.root.iterdir() if ID_RE.match(d.name) and (m := self.get(d.name)) is not None]
        return sorted(out, key=lambda m: (m.get("t", 0), m["id"]))

    def has(self, aid: str, sha256: str) -> bool:
        meta = self.get(aid)
        return meta is not None and meta.get("sha256") == sha256

    def install(self, meta: dict[str, Any], archive_path: Path) -> dict[str, Any]:
        """Check and unpack `archive_path` as assignment ``meta["id"]`` (replacing an older one of
        the same id). Raises ValueError (bad id or checksum) or archive.ArchiveRejected. Blocking."""
        aid = check_id(str(meta.get("id", "")))
        digest = sha256_file(archive_path)
        if digest != meta.get("sha256"):
            raise ValueError(f"assignment {aid}: the archive's checksum is not the one published")
        self.root.mkdir(parents=True, exist_ok=True)
        os.chmod(self.root, 0o755)  # the build user copies nothing from here, but the folder is not secret
        tmp = self.root / f".in-{aid}-{secrets.token_hex(4)}"
        tmp.mkdir(mode=0o755)
        try:
            manifest = archive.unpack(archive_path, tmp / "src", LIMITS)
            info = {
                "id": aid,
                "name": str(meta.get("name", aid))[:64],
                "sha256": digest,
                "by": str(meta.get("by", ""))[:64],
                "t": float(meta.get("t") or time.time()),
                "template": str(meta.get("template", ""))[:64],
                "files": len(manifest.files),
                "bytes": manifest.total,
                "received": time.time(),
            }
            (tmp / "assignment.json").write_text(json.dumps(info))
            final = self._folder(aid)
            old = None
            if final.exists():
                old = self.root / f".old-{aid}-{secrets.token_hex(4)}"
                os.rename(final, old)
            os.rename(tmp, final)
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)
            return info
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
