"""The room's assignment store in-process (xrflab/room/assignments.py): a template packed as a
student's upload would be, kept with its index across restarts, and the retained message it
publishes (the archive inline when small). test_room_assignments.py drives the same through a
broker, a room and benches."""

from __future__ import annotations

import base64
import hashlib
import io
import shutil
import tarfile
from pathlib import Path

import pytest

from xrflab.projects.archive import ArchiveRejected
from xrflab.room import payloads
from xrflab.room.assignments import RoomAssignments, template_archive

REPO = Path(__file__).resolve().parents[2]
BASE = REPO / "student_projects" / "templates" / "base"


def _members(data: bytes) -> dict[str, tarfile.TarInfo]:
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as t:
        return {m.name: m for m in t.getmembers()}


def test_a_template_is_packed_without_build_folders_links_or_owners(tmp_path: Path) -> None:
    tpl = tmp_path / "base"
    shutil.copytree(BASE, tpl, ignore=shutil.ignore_patterns("build"))
    (tpl / "build").mkdir()
    (tpl / "build" / "junk.o").write_bytes(b"\0")
    (tpl / "link").symlink_to("/etc/passwd")
    out = tmp_path / "base.tar.gz"
    template_archive(tpl, out)
    members = _members(out.read_bytes())
    assert "base/CMakeLists.txt" in members
    assert not [n for n in members if "/build/" in n or n.endswith("/link")]
    assert {(m.uid, m.gid, m.uname, m.mode) for m in members.values()} == {(0, 0, "", 0o644)}


def test_published_template_is_kept_indexed_and_announced_inline(tmp_path: Path) -> None:
    store = RoomAssignments(tmp_path / "assignments")
    meta = store.add_template("Lab 1 PID", BASE, by="teacher")
    archive = store.archive_path(meta["id"])
    assert meta["sha256"] == hashlib.sha256(archive.read_bytes()).hexdigest()
    assert meta["template"] == "base" and meta["files"] > 0 and meta["size"] == archive.stat().st_size
    assert not list((tmp_path / "assignments").glob(".tpl-*"))  # the temporary archive is gone

    msg = store.message(meta["id"])
    assert isinstance(msg, payloads.Assignment)
    assert msg.inline is not None and base64.b64decode(msg.inline) == archive.read_bytes()
    assert msg.path == f"/api/room/assignments/{meta['id']}/archive"

    again = RoomAssignments(tmp_path / "assignments")  # the room restarted
    assert [m["id"] for m in again.list()] == [meta["id"]]
    assert again.message(meta["id"]) == msg


def test_a_large_archive_is_fetched_not_inlined(tmp_path: Path) -> None:
    tpl = tmp_path / "big"
    shutil.copytree(BASE, tpl, ignore=shutil.ignore_patterns("build"))
    (tpl / "data.bin").write_bytes(_noise(payloads.INLINE_MAX + 1))
    store = RoomAssignments(tmp_path / "assignments")
    meta = store.add_template("Big", tpl, by="teacher")
    assert meta["size"] > payloads.INLINE_MAX
    assert store.message(meta["id"]).inline is None


def test_a_hostile_upload_is_refused_and_nothing_is_kept(tmp_path: Path) -> None:
    evil = tmp_path / "evil.tar.gz"
    with tarfile.open(evil, "w:gz") as t:
        info = tarfile.TarInfo("../escape.txt")
        info.size = 1
        t.addfile(info, io.BytesIO(b"x"))
    store = RoomAssignments(tmp_path / "assignments")
    with pytest.raises(ArchiveRejected):
        store.add("Evil", evil, by="teacher")
    assert store.list() == [] and not (tmp_path / "assignments" / "index.json").exists()


def _noise(n: int) -> bytes:
    """Bytes gzip cannot shrink (so the archive really is larger than INLINE_MAX)."""
    out = bytearray()
    block = b"seed"
    while len(out) < n:
        block = hashlib.sha256(block).digest()
        out += block
    return bytes(out[:n])
