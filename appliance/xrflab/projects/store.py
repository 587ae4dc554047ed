"""Projects and their builds in SQLite.

A project belongs to an ``owner`` (the account id once accounts exist; ``local`` before) and
lives in its own folder under the data dir (``projects/<folder>/src``: the unpacked source;
``projects/<folder>/builds/<id>``: one folder per build; ``projects/<folder>/v<n>``: source
version n, which is what a build compiles, see versions.py). Folder names are random, so they say
nothing about the owner and cannot be guessed by another student's build.

Every build is kept: source hash, toolchain, duration, result, log path, the executable and
what the page shows of it (20-sim tokens, message fields, compiler diagnostics). Runs of a
project build are linked in ``project_runs``.

Each table's record is defined once, below (records.py: a dataclass whose fields carry their
SQLite declaration and API description): the tables, the rows read back and the API's models
(``<Row>.api_model()``, used by routes_projects and routes_editor) are made from it.

Used from the event loop and from the build thread: one connection, a lock, autocommit, WAL.
"""

from __future__ import annotations

import sqlite3
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Literal

from ..private_files import private_db
from ..records import (
    Record,
    Served,
    add_missing_columns,
    api_model,
    column,
    column_names,
    create_table,
    from_sql,
    served,
    to_sql,
)

BuildStatus = Literal["queued", "building", "ok", "failed"]

if TYPE_CHECKING:
    from pydantic import BaseModel

# What a record's answer in the API adds to its served columns: computed by the row's as_dict(),
# declared here once for its API model (the row's api_model()).
Computed = dict[str, Served]


@dataclass
class ProjectRow:
    """A project: THE definition. The table ``projects`` and the API's Project (``api_model()``)
    are made from it (tests/projects/test_project_record.py)."""

    id: int = column("INTEGER PRIMARY KEY AUTOINCREMENT")
    owner: str = column("TEXT NOT NULL", "username of the project's owner")
    name: str = column("TEXT NOT NULL")
    # Random (routes_projects._new_folder): says nothing about the owner, and is not served, so
    # another student's build cannot be pointed at it.
    folder: str = column("TEXT NOT NULL UNIQUE", api=False)
    created: float = column("REAL NOT NULL", "Unix time")
    updated: float = column("REAL NOT NULL", "Unix time of the last change")
    source_hash: str = column("TEXT NOT NULL DEFAULT ''", "the source hash of the newest build asked for")
    origin: str = column("TEXT NOT NULL DEFAULT ''", "upload | template:<name> | assignment:<id>")
    files: int = column("INTEGER NOT NULL DEFAULT 0", "files in the source")
    bytes: int = column("INTEGER NOT NULL DEFAULT 0", "their total size")

    COMPUTED: ClassVar[Computed] = {}

    def as_dict(self) -> dict[str, Any]:
        return served(self)

    @classmethod
    def api_model(cls, name: str = "Project", **extra: tuple[Any, Any]) -> type[BaseModel]:
        return api_model(cls, name, {**cls.COMPUTED, **extra})


@dataclass
class BuildRow:
    """A build of a project: THE definition (table ``project_builds``, the API's Build)."""

    id: int = column("INTEGER PRIMARY KEY AUTOINCREMENT")
    project_id: int = column("INTEGER NOT NULL REFERENCES projects(id) ON DELETE CASCADE")
    owner: str = column("TEXT NOT NULL", "the project's owner")
    source_hash: str = column(
        "TEXT NOT NULL", "hash of the source built: the same source with the same toolchain is not built again"
    )
    toolchain: str = column("TEXT NOT NULL DEFAULT ''", "cmake's and the compiler's versions, rt_core's hash")
    status: BuildStatus = column("TEXT NOT NULL")
    result: str = column("TEXT NOT NULL DEFAULT ''", "one line a student reads")
    queued: float = column("REAL NOT NULL", "Unix time")
    started: float | None = column("REAL", "Unix time; null while queued")
    ended: float | None = column("REAL", "Unix time; null until it ends")
    duration: float | None = column("REAL", "seconds")
    # Where the appliance keeps the build's output: its business, not the API's.
    log_path: str = column("TEXT NOT NULL DEFAULT ''", api=False)
    executable: str = column("TEXT NOT NULL DEFAULT ''", api=False)
    details: dict[str, Any] = column(
        "TEXT NOT NULL DEFAULT '{}'",
        "diagnostics, twenty_sim, messages, cycle_freq, sandbox",
        json_text=True,
        default_factory=dict,
    )

    COMPUTED: ClassVar[Computed] = {
        "runnable": Served(bool, "the build succeeded: POST .../builds/{id}/run starts it"),
    }

    def as_dict(self) -> dict[str, Any]:
        return {**served(self), "runnable": self.status == "ok"}

    @classmethod
    def api_model(cls, name: str = "Build", **extra: tuple[Any, Any]) -> type[BaseModel]:
        return api_model(cls, name, {**cls.COMPUTED, **extra})


@dataclass
class VersionRow:
    """A source version of a project (versions.py keeps its files): THE definition (table
    ``project_versions``, the API's Version)."""

    id: int = column("INTEGER PRIMARY KEY AUTOINCREMENT", api=False)
    project_id: int = column("INTEGER NOT NULL REFERENCES projects(id) ON DELETE CASCADE", api=False)
    n: int = column("INTEGER NOT NULL", "1, 2, ... within the project")
    source_hash: str = column("TEXT NOT NULL", "hash of the version's tree: the key its builds are found by")
    created: float = column("REAL NOT NULL", "Unix time")
    author: str = column("TEXT NOT NULL", "username of who made it")
    origin: str = column(
        "TEXT NOT NULL", "upload <file> | template:<name> | assignment:<id> | edit <path> | delete <path> | ..."
    )
    # path -> sha256 of the content; the API serves how many (COMPUTED, in this field's place).
    files: dict[str, str] = column("TEXT NOT NULL DEFAULT '{}'", api=False, json_text=True, default_factory=dict)

    CONSTRAINTS: ClassVar[tuple[str, ...]] = ("UNIQUE (project_id, n)",)
    COMPUTED: ClassVar[Computed] = {"files": Served(int, "how many files the version has")}

    def as_dict(self) -> dict[str, Any]:
        return {**served(self), "files": len(self.files)}

    @classmethod
    def api_model(cls, name: str = "Version", **extra: tuple[Any, Any]) -> type[BaseModel]:
        return api_model(cls, name, {**cls.COMPUTED, **extra})


@dataclass
class RunLinkRow:
    """A run of a project build (its record is the run store's): THE definition of the table
    ``project_runs`` and of a project's ``runs`` in the API."""

    run_id: int = column("INTEGER PRIMARY KEY", "the run (GET /api/runs/{run_id})")
    build_id: int = column("INTEGER NOT NULL", "the build that ran")
    project_id: int = column("INTEGER NOT NULL", api=False)
    owner: str = column("TEXT NOT NULL", api=False)

    COMPUTED: ClassVar[Computed] = {}

    def as_dict(self) -> dict[str, Any]:
        return served(self)

    @classmethod
    def api_model(cls, name: str = "ProjectRun", **extra: tuple[Any, Any]) -> type[BaseModel]:
        return api_model(cls, name, {**cls.COMPUTED, **extra})


@dataclass
class AssignmentCopyRow:
    """The copy of a room's assignment made for a student (assignments.py): made once, so a copy
    the student deleted is not made again. Not served."""

    assignment: str = column("TEXT NOT NULL")
    owner: str = column("TEXT NOT NULL")
    project_id: int = column("INTEGER NOT NULL")
    created: float = column("REAL NOT NULL")

    CONSTRAINTS: ClassVar[tuple[str, ...]] = ("PRIMARY KEY (assignment, owner)",)


# Every table of the store: its name, its record. The indexes are the store's own (not records).
TABLES: dict[str, type[Record]] = {
    "projects": ProjectRow,
    "project_builds": BuildRow,
    "project_versions": VersionRow,
    "project_runs": RunLinkRow,
    "assignment_copies": AssignmentCopyRow,
}
_INDEXES = """
CREATE INDEX IF NOT EXISTS projects_owner ON projects(owner);
CREATE INDEX IF NOT EXISTS builds_project ON project_builds(project_id);
"""


def schema() -> str:
    """CREATE TABLE for every table (from its record), then the indexes."""
    tables = "".join(create_table(t, r, getattr(r, "CONSTRAINTS", ())) for t, r in TABLES.items())
    return tables + _INDEXES


_PCOLS = column_names(ProjectRow)
_BCOLS = column_names(BuildRow)
_VCOLS = column_names(VersionRow)
_LCOLS = column_names(RunLinkRow)


class ProjectStore:
    def __init__(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        private_db(path)  # 0600 before SQLite opens it: its WAL/SHM take the same mode
        self._db = sqlite3.connect(str(path), isolation_level=None, check_same_thread=False)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA foreign_keys=ON")
        self._db.executescript(schema())
        for table, record in TABLES.items():
            add_missing_columns(self._db, table, record)
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
        values = to_sql(ProjectRow, values)
        values.setdefault("updated", time.time())
        self._x(f"UPDATE projects SET {', '.join(k + '=?' for k in values)} WHERE id=?", (*values.values(), pid))
        row = self.project(pid)
        assert row is not None
        return row

    def project(self, pid: int) -> ProjectRow | None:
        if not -(2**63) <= pid < 2**63:  # beyond SQLite's INTEGER (a guessed or fuzzed id): none
            return None
        r = self._q(f"SELECT {', '.join(_PCOLS)} FROM projects WHERE id=?", (pid,))
        return _project(r[0]) if r else None

    def projects(self, owner: str | None = None) -> list[ProjectRow]:
        if owner is None:
            rows = self._q(f"SELECT {', '.join(_PCOLS)} FROM projects ORDER BY id DESC")
        else:
            rows = self._q(f"SELECT {', '.join(_PCOLS)} FROM projects WHERE owner=? ORDER BY id DESC", (owner,))
        return [_project(r) for r in rows]

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
                (
                    project_id,
                    source_hash,
                    time.time(),
                    author,
                    origin,
                    to_sql(VersionRow, {"files": files})["files"],
                    project_id,
                ),
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
        values = to_sql(BuildRow, values)
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

    def runs_of(self, project_id: int) -> list[dict[str, Any]]:
        """The project's runs as the API serves them (RunLinkRow's served fields), newest first."""
        rows = self._q(
            f"SELECT {', '.join(_LCOLS)} FROM project_runs WHERE project_id=? ORDER BY run_id DESC", (project_id,)
        )
        return [_link(r).as_dict() for r in rows]

    def projects_with_origin(self, origin: str) -> list[ProjectRow]:
        rows = self._q(f"SELECT {', '.join(_PCOLS)} FROM projects WHERE origin=? ORDER BY id", (origin,))
        return [_project(r) for r in rows]

    def copies_made(self, owner: str) -> set[str]:
        """The assignments a copy was made of for `owner` (deleted since or not)."""
        return {r[0] for r in self._q("SELECT assignment FROM assignment_copies WHERE owner=?", (owner,))}

    def record_copy(self, assignment: str, owner: str, project_id: int) -> None:
        self._x(
            "INSERT OR IGNORE INTO assignment_copies (assignment, owner, project_id, created) VALUES (?, ?, ?, ?)",
            (assignment, owner, project_id, time.time()),
        )

    def run_link(self, run_id: int) -> RunLinkRow | None:
        r = self._q(f"SELECT {', '.join(_LCOLS)} FROM project_runs WHERE run_id=?", (run_id,))
        return _link(r[0]) if r else None


# A row SELECTed in its record's column order, as its record (records.from_sql: JSON decoded).
def _project(r: tuple[Any, ...]) -> ProjectRow:
    return from_sql(ProjectRow, r)


def _build(r: tuple[Any, ...]) -> BuildRow:
    return from_sql(BuildRow, r)


def _version(r: tuple[Any, ...]) -> VersionRow:
    return from_sql(VersionRow, r)


def _link(r: tuple[Any, ...]) -> RunLinkRow:
    return from_sql(RunLinkRow, r)
