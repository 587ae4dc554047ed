"""xrflab/private_files.py: a database file and its SQLite side files are 0600 whatever the umask,
and a symbolic link is never followed (it could point at a file of someone else's)."""

from __future__ import annotations

import os
import sqlite3
import stat
from pathlib import Path

from xrflab.private_files import private_db


def _mode(p: Path) -> int:
    return stat.S_IMODE(p.lstat().st_mode)


def test_created_private_under_a_permissive_umask(tmp_path: Path) -> None:
    db = tmp_path / "sub" / "x.db"
    old = os.umask(0)
    try:
        private_db(db)
    finally:
        os.umask(old)
    assert db.exists() and _mode(db) == 0o600
    # SQLite's side files take the database's mode
    con = sqlite3.connect(db)
    try:
        con.execute("pragma journal_mode=wal")
        con.execute("create table t (x)")
        con.commit()
        assert _mode(db.with_name("x.db-wal")) == 0o600
    finally:
        con.close()


def test_an_existing_file_and_its_side_files_are_narrowed_but_kept(tmp_path: Path) -> None:
    db = tmp_path / "x.db"
    db.write_bytes(b"content")
    db.chmod(0o644)
    wal = tmp_path / "x.db-wal"
    wal.write_bytes(b"")
    wal.chmod(0o666)
    private_db(db)
    assert _mode(db) == 0o600 and db.read_bytes() == b"content"
    assert _mode(wal) == 0o600


def test_a_linked_side_file_is_not_followed(tmp_path: Path) -> None:
    target = tmp_path / "someone_elses"
    target.write_text("x")
    target.chmod(0o644)
    db = tmp_path / "x.db"
    (tmp_path / "x.db-shm").symlink_to(target)
    private_db(db)
    assert _mode(target) == 0o644  # the link's target is untouched
