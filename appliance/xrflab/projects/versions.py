"""Source versions of a project: every state its source has been in, kept, and what a build compiles.

A project's working copy is ``projects/<folder>/src`` (what an upload unpacks, a template is copied
to, the editor saves into). Every change to it — an upload, a new project from a template, each
save or delete in the browser's editor — is recorded here as the project's next **version**: an
immutable copy of the tree in ``projects/<folder>/v<n>`` plus a row in the store
(``project_versions``: number, author, origin, the content hash of every file).

Why a copy per version, and why builds compile it rather than ``src``: a build is queued and may
start minutes later; compiling the live working copy would compile whatever was saved last, while
the build row names the source hash it was queued with. A student saving twice quickly would then
run code that is not the build they clicked. A version's tree never changes, so "build and run"
runs exactly the source that was saved. Unchanged files are hard links to the previous version's
(same content, read-only), so a version costs the files that changed, not the whole project.

The version's ``source_hash`` is ``build_key.source_hash`` of its tree: the key builds are reused by,
so a version and its builds are found from each other.

Diffs (between two versions, or a version and a template as it is in the appliance: what the
student wrote on top of what they started from) are computed here with difflib.
"""

from __future__ import annotations

import difflib
import os
import secrets
import shutil
import stat
import threading
from pathlib import Path
from typing import Any

from . import archive
from .build_key import source_hash
from .digest import sha256_file
from .store import ProjectRow, ProjectStore, VersionRow

# Larger files are not diffed line by line (their change is still listed).
DIFF_MAX_BYTES = 1 << 20
DIFF_MAX_LINES = 20000


def file_hashes(tree: Path) -> dict[str, str]:
    """path -> sha256 of every regular file under ``tree`` (links are not followed, skipped)."""
    out: dict[str, str] = {}
    for dirpath, dirnames, filenames in os.walk(tree):
        dirnames.sort()
        for f in sorted(filenames):
            p = Path(dirpath) / f
            if p.is_symlink() or not p.is_file():
                continue
            out[p.relative_to(tree).as_posix()] = sha256_file(p)
    return out


class Versions:
    """The versions of every project under ``root`` (the projects folder)."""

    def __init__(self, store: ProjectStore, root: Path) -> None:
        self.store = store
        self.root = root
        self._locks: dict[int, threading.Lock] = {}
        self._locks_lock = threading.Lock()

    def lock(self, project: ProjectRow) -> threading.Lock:
        """Held while a project's working copy changes and is recorded: two saves (two tabs) never
        interleave between writing ``src`` and snapshotting it."""
        with self._locks_lock:
            return self._locks.setdefault(project.id, threading.Lock())

    def tree(self, project: ProjectRow, version: VersionRow) -> Path:
        return self.root / project.folder / f"v{version.n}"

    def record(self, project: ProjectRow, author: str, origin: str) -> tuple[VersionRow, bool]:
        """The working copy as the project's next version; (version, new). A working copy equal to
        the latest version is not recorded again: (latest, False). The caller holds lock(project)
        when it changed ``src`` (so what is recorded is what it wrote)."""
        folder = self.root / project.folder
        src = folder / "src"
        latest = self.store.latest_version(project.id)
        prev_tree = self.tree(project, latest) if latest else None
        tmp = folder / f".v-new-{secrets.token_hex(4)}"
        try:
            hashes = self._copy(src, tmp, latest.files if latest else {}, prev_tree)
            digest = source_hash(tmp)
            if latest is not None and latest.source_hash == digest and prev_tree is not None and prev_tree.is_dir():
                return latest, False
            row = self.store.add_version(project.id, digest, author, origin, hashes)
            target = self.tree(project, row)
            if target.exists():  # a leftover of a version row that was never written (a crash): replaced
                shutil.rmtree(target)
            os.rename(tmp, target)
            return row, True
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)

    def current(self, project: ProjectRow, author: str) -> VersionRow:
        """The version the working copy is: the latest, or a new one when ``src`` was changed
        without being recorded (a project from before versions existed)."""
        with self.lock(project):
            return self.record(project, author, "existing source")[0]

    @staticmethod
    def _copy(src: Path, dest: Path, prev: dict[str, str], prev_tree: Path | None) -> dict[str, str]:
        """``src`` into ``dest``: an unchanged file (same path, same content as the previous version)
        is a hard link to it, the others are copies; everything read-only (a version never changes)."""
        hashes: dict[str, str] = {}
        dest.mkdir(mode=0o700)
        for dirpath, dirnames, filenames in os.walk(src):
            dirnames.sort()
            rel_dir = Path(dirpath).relative_to(src)
            for d in dirnames:
                (dest / rel_dir / d).mkdir(mode=0o700)
            for f in sorted(filenames):
                p = Path(dirpath) / f
                st = os.lstat(p)
                if not stat.S_ISREG(st.st_mode):
                    continue  # an archive brings no links; anything else is not source
                rel = (rel_dir / f).as_posix()
                digest = sha256_file(p)
                hashes[rel] = digest
                out = dest / rel
                if prev_tree is not None and prev.get(rel) == digest:
                    try:
                        os.link(prev_tree / rel, out)
                        continue
                    except OSError:
                        pass  # the previous tree is gone or on another file system: a copy
                shutil.copyfile(p, out)
                os.chmod(out, 0o500 if st.st_mode & 0o100 else 0o400)
        return hashes

    # -- reading -----------------------------------------------------------------------------------

    def read(self, project: ProjectRow, version: VersionRow, rel: str) -> bytes | None:
        if rel not in version.files:
            return None
        p = self.tree(project, version) / rel
        fd = os.open(p, os.O_RDONLY | os.O_NOFOLLOW)
        with os.fdopen(fd, "rb") as f:
            return f.read(DIFF_MAX_BYTES + 1)


def template_side(template_dir: Path) -> tuple[dict[str, str], Any]:
    """(path -> sha256, reader) of a template folder as the appliance has it now."""
    hashes = {k: v for k, v in file_hashes(template_dir).items() if k.split("/", 1)[0] not in archive.SKIPPED_DIRS}

    def read(rel: str) -> bytes | None:
        p = template_dir / rel
        if rel not in hashes or p.is_symlink():
            return None
        with open(p, "rb") as f:
            return f.read(DIFF_MAX_BYTES + 1)

    return hashes, read


def _text(data: bytes | None) -> list[str] | None:
    """The lines of a text file, or None for a binary or too large one."""
    if data is None or len(data) > DIFF_MAX_BYTES or b"\0" in data:
        return None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        return None
    lines = text.splitlines(keepends=True)
    return lines if len(lines) <= DIFF_MAX_LINES else None


def diff(
    a_files: dict[str, str],
    read_a: Any,
    b_files: dict[str, str],
    read_b: Any,
    a_name: str,
    b_name: str,
    context: int = 3,
) -> list[dict[str, Any]]:
    """Per file that differs: path, status (added | removed | modified), lines added/removed and a
    unified diff (``None`` for a binary or oversized file, whose change is still listed)."""
    out: list[dict[str, Any]] = []
    for path in sorted(set(a_files) | set(b_files)):
        ha, hb = a_files.get(path), b_files.get(path)
        if ha == hb:
            continue
        status = "added" if ha is None else "removed" if hb is None else "modified"
        la = [] if ha is None else _text(read_a(path))
        lb = [] if hb is None else _text(read_b(path))
        entry: dict[str, Any] = {"path": path, "status": status, "added": 0, "removed": 0, "diff": None}
        if la is not None and lb is not None:
            lines = list(difflib.unified_diff(la, lb, f"{a_name}/{path}", f"{b_name}/{path}", n=context))
            entry["added"] = sum(1 for x in lines[2:] if x.startswith("+"))
            entry["removed"] = sum(1 for x in lines[2:] if x.startswith("-"))
            # A last line without a newline still gets its own line in the diff.
            entry["diff"] = "".join(x if x.endswith("\n") else x + "\n\\ No newline at end of file\n" for x in lines)
        out.append(entry)
    return out
