"""Projects and their builds in SQLite.

A project belongs to an ``owner`` (the account id once accounts exist; ``local`` before) and
lives in its own folder under the data dir (``projects/<folder>/src``: the unpacked source;
``projects/<folder>/builds/<id>``: one folder per build; ``projects/<folder>/v<n>``: source
version n, which is what a build compiles, see versions.py). Folder names are random, so they say
nothing about the owner and cannot be guessed by another student's build.

Every build is kept: source hash, toolchain, duration, result, log path, the executable and
what the page shows of it (20-sim tokens, message fields, compiler diagnostics). Runs of a
project build are linked in ``project_runs``.

Used from the event loop and from the build thread: one connection, a lock, autocommit, WAL.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from ..server.private_files import private_db

_SCHEMA = """
CREATE TABLE IF NOT EXISTS projects (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    owner TEXT NOT NULL,
    name TEXT NOT NULL,
    folder TEXT NOT NULL UNIQUE,
    created REAL NOT NULL,
    updated REAL NOT NULL,
    source_hash TEXT NOT NULL DEFAULT '',
    origin TEXT NOT NULL DEFAULT '',      -- upload | template:<name>
    files INTEGER NOT NULL DEFAULT 0,
    bytes INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS projects_owner ON projects(owner);
CREATE TABLE IF NOT EXISTS project_builds (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    project_id INTEGER NOT NULL REFERENCES projects(id) ON DELETE CASCADE,
    owner TEXT NOT NULL,
    source_hash TEXT NOT NULL,
    toolchain TEXT NOT NULL DEFAULT '',
    status TEXT NOT NULL,                 -- queued | building | ok | failed
    result TEXT NOT NULL DEFAULT '',      -- one line a student reads
    queued REAL NOT NULL,
    started REAL,
    ended REAL,
    duration REAL,
    log_path TEXT NOT NULL DEFAULT '',
    executable TEXT NOT NULL DEFAULT '',
    details TEXT NOT NULL DEFAULT '{}'    -- JSON: diagnostics, twenty_sim, messages, cycle_freq, sandbox
);
CREATE INDEX IF NOT EXISTS builds_project ON project_builds(project_id);
-- Every state of a project's source (upload, template, each save in the editor): versions.py.
CREATE TABLE IF NOT EXISTS project_versions (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    project_id INTEGER NOT NULL REFERENCES projects(id) ON DELETE CASCADE,
    n INTEGER NOT NULL,                   -- 1, 2, ... within the project
    source_hash TEXT NOT NULL,            -- builder.source_hash of the tree: the builds' key
    created REAL NOT NULL,
    author TEXT NOT NULL,
    origin TEXT NOT NULL,                 -- upload | template:<name> | edit <path> | delete <path> | ...
    files TEXT NOT NULL DEFAULT '{}',     -- JSON: path -> sha256 of the content
    UNIQUE (project_id, n)
);
CREATE TABLE IF NOT EXISTS project_runs (
    run_id INTEGER PRIMARY KEY,
    build_id INTEGER NOT NULL,
    project_id INTEGER NOT NULL,
    owner TEXT NOT NULL
);
-- The copy of a room's assignment made for a student (assignments.py): made once, so a copy the
-- student deleted is not made again.
CREATE TABLE IF NOT EXISTS assignment_copies (
    assignment TEXT NOT NULL,
    owner TEXT NOT NULL,
    project_id INTEGER NOT NULL,
    created REAL NOT NULL,
    PRIMARY KEY (assignment, owner)
);
"""


@dataclass
class ProjectRow:
    id: int
    owner: str
    name: str
    folder: str
    created: float
    updated: float
    source_hash: str
    origin: str
    files: int
    bytes: int

    def as_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "folder"}


@dataclass
class BuildRow:
    id: int
    project_id: int
    owner: str
    source_hash: str
    toolchain: str
    status: str
    result: str
    queued: float
    started: float | None
    ended: float | None
    duration: float | None
    log_path: str
    executable: str
    details: dict[str, Any]

    def as_dict(self) -> dict[str, Any]:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d.pop("log_path")
        d.pop("executable")
        d["runnable"] = self.status == "ok"
        return d


@dataclass
class VersionRow:
    id: int
    project_id: int
    n: int
    source_hash: str
    created: float
    author: str
    origin: str
    files: dict[str, str]

    def as_dict(self) -> dict[str, Any]:
        return {
            "n": self.n,
            "source_hash": self.source_hash,
            "created": self.created,
            "author": self.author,
            "origin": self.origin,
            "files": len(self.files),
        }


_VCOLS = [f.name for f in fields(VersionRow)]
_PCOLS = [f.name for f in fields(ProjectRow)]
_BCOLS = [f.name for f in fields(BuildRow)]


class ProjectStore:
    def __init__(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        private_db(path)  # 0600 before SQLite opens it: its WAL/SHM take the same mode
        self._db = sqlite3.connect(str(path), isolation_level=None, check_same_thread=False)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA foreign_keys=ON")
        self._db.executescript(_SCHEMA)
        # Builds a previous appliance process left unfinished did not finish.
        self._db.execute(
            "UPDATE project_builds SET status='failed', result='the appliance stopped during this build', "
            "ended=COALESCE(ended, ?) WHERE status IN ('queued', 'building')",
            (time.time(),),
        )

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def _q(self, sql: str, args: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
        with self._lock:
            return self._db.execute(sql, args).fetchall()

    def _x(self, sql: str, args: tuple[Any, ...] = ()) -> int:
        with self._lock:
            cur = self._db.execute(sql, args)
            return int(cur.lastrowid or 0)

    # -- projects -------------------------------------------------------------------------------

    def create_project(self, owner: str, name: str, folder: str, origin: str) -> ProjectRow:
        now = time.time()
        pid = self._x(
            "INSERT INTO projects (owner, name, folder, created, updated, origin) VALUES (?, ?, ?, ?, ?, ?)",
            (owner, name, folder, now, now, origin),
        )
        row = self.project(pid)
        assert row is not None
        return row

    def update_project(self, pid: int, **values: Any) -> ProjectRow:
        unknown = set(values) - set(_PCOLS)
        if unknown:
            raise KeyError(sorted(unknown))
        values.setdefault("updated", time.time())
        self._x(f"UPDATE projects SET {', '.join(k + '=?' for k in values)} WHERE id=?", (*values.values(), pid))
        row = self.project(pid)
        assert row is not None
        return row

    def project(self, pid: int) -> ProjectRow | None:
        if not -(2**63) <= pid < 2**63:  # beyond SQLite's INTEGER (a guessed or fuzzed id): none
            return None
        r = self._q(f"SELECT {', '.join(_PCOLS)} FROM projects WHERE id=?", (pid,))
        return ProjectRow(*r[0]) if r else None

    def projects(self, owner: str | None = None) -> list[ProjectRow]:
        if owner is None:
            rows = self._q(f"SELECT {', '.join(_PCOLS)} FROM projects ORDER BY id DESC")
        else:
            rows = self._q(f"SELECT {', '.join(_PCOLS)} FROM projects WHERE owner=? ORDER BY id DESC", (owner,))
        return [ProjectRow(*r) for r in rows]

    def delete_project(self, pid: int) -> None:
        self._x("DELETE FROM project_versions WHERE project_id=?", (pid,))
        self._x("DELETE FROM project_builds WHERE project_id=?", (pid,))
        self._x("DELETE FROM projects WHERE id=?", (pid,))

    # -- source versions (versions.py keeps their files) -----------------------------------------

    def add_version(
        self, project_id: int, source_hash: str, author: str, origin: str, files: dict[str, str]
    ) -> VersionRow:
        """The project's next version number, taken and written in one transaction."""
        with self._lock:
            cur = self._db.execute(
                "INSERT INTO project_versions (project_id, n, source_hash, created, author, origin, files) "
                "SELECT ?, COALESCE(MAX(n), 0) + 1, ?, ?, ?, ?, ? FROM project_versions WHERE project_id=?",
                (project_id, source_hash, time.time(), author, origin, json.dumps(files), project_id),
            )
            vid = int(cur.lastrowid or 0)
        rows = self._q(f"SELECT {', '.join(_VCOLS)} FROM project_versions WHERE id=?", (vid,))
        return _version(rows[0])

    def versions(self, project_id: int) -> list[VersionRow]:
        rows = self._q(
            f"SELECT {', '.join(_VCOLS)} FROM project_versions WHERE project_id=? ORDER BY n DESC", (project_id,)
        )
        return [_version(r) for r in rows]

    def version(self, project_id: int, n: int) -> VersionRow | None:
        if not -(2**63) <= n < 2**63:
            return None
        rows = self._q(f"SELECT {', '.join(_VCOLS)} FROM project_versions WHERE project_id=? AND n=?", (project_id, n))
        return _version(rows[0]) if rows else None

    def latest_version(self, project_id: int) -> VersionRow | None:
        rows = self._q(
            f"SELECT {', '.join(_VCOLS)} FROM project_versions WHERE project_id=? ORDER BY n DESC LIMIT 1",
            (project_id,),
        )
        return _version(rows[0]) if rows else None

    # -- builds ---------------------------------------------------------------------------------

    def create_build(self, project: ProjectRow, source_hash: str, toolchain: str) -> BuildRow:
        bid = self._x(
            "INSERT INTO project_builds (project_id, owner, source_hash, toolchain, status, queued) "
            "VALUES (?, ?, ?, ?, 'queued', ?)",
            (project.id, project.owner, source_hash, toolchain, time.time()),
        )
        row = self.build(bid)
        assert row is not None
        return row

    def update_build(self, bid: int, **values: Any) -> BuildRow:
        unknown = set(values) - set(_BCOLS)
        if unknown:
            raise KeyError(sorted(unknown))
        if "details" in values:
            values["details"] = json.dumps(values["details"])
        self._x(f"UPDATE project_builds SET {', '.join(k + '=?' for k in values)} WHERE id=?", (*values.values(), bid))
        row = self.build(bid)
        assert row is not None
        return row

    def build(self, bid: int) -> BuildRow | None:
        if not -(2**63) <= bid < 2**63:  # beyond SQLite's INTEGER (a guessed or fuzzed id): none
            return None
        r = self._q(f"SELECT {', '.join(_BCOLS)} FROM project_builds WHERE id=?", (bid,))
        return _build(r[0]) if r else None

    def builds(self, project_id: int, limit: int = 50) -> list[BuildRow]:
        rows = self._q(
            f"SELECT {', '.join(_BCOLS)} FROM project_builds WHERE project_id=? ORDER BY id DESC LIMIT ?",
            (project_id, limit),
        )
        return [_build(r) for r in rows]

    def reusable(self, project_id: int, source_hash: str, toolchain: str) -> BuildRow | None:
        """The newest successful build of exactly this source with this toolchain, if its executable is still there."""
        rows = self._q(
            f"SELECT {', '.join(_BCOLS)} FROM project_builds WHERE project_id=? AND source_hash=? "
            "AND toolchain=? AND status='ok' ORDER BY id DESC LIMIT 1",
            (project_id, source_hash, toolchain),
        )
        if not rows:
            return None
        b = _build(rows[0])
        return b if b.executable and Path(b.executable).exists() else None

    def link_run(self, run_id: int, build: BuildRow) -> None:
        self._x(
            "INSERT OR REPLACE INTO project_runs (run_id, build_id, project_id, owner) VALUES (?, ?, ?, ?)",
            (run_id, build.id, build.project_id, build.owner),
        )

    def runs_of(self, project_id: int) -> list[dict[str, int]]:
        return [
            {"run_id": r[0], "build_id": r[1]}
            for r in self._q(
                "SELECT run_id, build_id FROM project_runs WHERE project_id=? ORDER BY run_id DESC", (project_id,)
            )
        ]

    def projects_with_origin(self, origin: str) -> list[ProjectRow]:
        rows = self._q(f"SELECT {', '.join(_PCOLS)} FROM projects WHERE origin=? ORDER BY id", (origin,))
        return [ProjectRow(*r) for r in rows]

    def copies_made(self, owner: str) -> set[str]:
        """The assignments a copy was made of for `owner` (deleted since or not)."""
        return {r[0] for r in self._q("SELECT assignment FROM assignment_copies WHERE owner=?", (owner,))}

    def record_copy(self, assignment: str, owner: str, project_id: int) -> None:
        self._x(
            "INSERT OR IGNORE INTO assignment_copies (assignment, owner, project_id, created) VALUES (?, ?, ?, ?)",
            (assignment, owner, project_id, time.time()),
        )

    def run_link(self, run_id: int) -> dict[str, Any] | None:
        r = self._q("SELECT run_id, build_id, project_id, owner FROM project_runs WHERE run_id=?", (run_id,))
        return dict(zip(("run_id", "build_id", "project_id", "owner"), r[0])) if r else None


def _build(r: tuple[Any, ...]) -> BuildRow:
    d = dict(zip(_BCOLS, r))
    d["details"] = json.loads(d["details"] or "{}")
    return BuildRow(**d)


def _version(r: tuple[Any, ...]) -> VersionRow:
    d = dict(zip(_VCOLS, r))
    d["files"] = json.loads(d["files"] or "{}")
    return VersionRow(**d)
