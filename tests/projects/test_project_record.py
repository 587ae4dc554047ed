"""The project records have one definition each (projects/store.py: ProjectRow, BuildRow,
VersionRow, RunLinkRow, AssignmentCopyRow): the SQL tables and the API's Project, Build, Version,
ProjectRun and ProjectDetail are made from them, so they cannot disagree (they were written four
times: the SQL text, the row classes, routes_projects' and routes_editor's models)."""

from __future__ import annotations

import sqlite3
import subprocess
import sys
from pathlib import Path
from typing import Any

from xrflab.projects.store import TABLES, BuildRow, ProjectRow, ProjectStore, RunLinkRow, VersionRow
from xrflab.records import column_names

# The tables as the release before the one definition created them (the SQL text store.py had):
# an appliance upgraded from it keeps its projects, and the tables made now are the same.
FIRST_RELEASE = """
CREATE TABLE projects (
    id INTEGER PRIMARY KEY AUTOINCREMENT, owner TEXT NOT NULL, name TEXT NOT NULL,
    folder TEXT NOT NULL UNIQUE, created REAL NOT NULL, updated REAL NOT NULL,
    source_hash TEXT NOT NULL DEFAULT '', origin TEXT NOT NULL DEFAULT '',
    files INTEGER NOT NULL DEFAULT 0, bytes INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX projects_owner ON projects(owner);
CREATE TABLE project_builds (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    project_id INTEGER NOT NULL REFERENCES projects(id) ON DELETE CASCADE,
    owner TEXT NOT NULL, source_hash TEXT NOT NULL, toolchain TEXT NOT NULL DEFAULT '',
    status TEXT NOT NULL, result TEXT NOT NULL DEFAULT '', queued REAL NOT NULL,
    started REAL, ended REAL, duration REAL, log_path TEXT NOT NULL DEFAULT '',
    executable TEXT NOT NULL DEFAULT '', details TEXT NOT NULL DEFAULT '{}'
);
CREATE INDEX builds_project ON project_builds(project_id);
CREATE TABLE project_versions (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    project_id INTEGER NOT NULL REFERENCES projects(id) ON DELETE CASCADE,
    n INTEGER NOT NULL, source_hash TEXT NOT NULL, created REAL NOT NULL, author TEXT NOT NULL,
    origin TEXT NOT NULL, files TEXT NOT NULL DEFAULT '{}',
    UNIQUE (project_id, n)
);
CREATE TABLE project_runs (
    run_id INTEGER PRIMARY KEY, build_id INTEGER NOT NULL, project_id INTEGER NOT NULL, owner TEXT NOT NULL
);
CREATE TABLE assignment_copies (
    assignment TEXT NOT NULL, owner TEXT NOT NULL, project_id INTEGER NOT NULL, created REAL NOT NULL,
    PRIMARY KEY (assignment, owner)
);
INSERT INTO projects (owner, name, folder, created, updated, origin) VALUES ('ann', 'p', 'f00d', 1.0, 2.0, 'upload');
INSERT INTO project_builds (project_id, owner, source_hash, status, queued, details)
    VALUES (1, 'ann', 'abc', 'ok', 3.0, '{"cycle_freq": 1000}');
INSERT INTO project_versions (project_id, n, source_hash, created, author, origin, files)
    VALUES (1, 1, 'abc', 1.0, 'ann', 'upload', '{"src/main.cpp": "00"}');
INSERT INTO project_runs (run_id, build_id, project_id, owner) VALUES (7, 1, 1, 'ann');
"""

# What the API serves of each record beyond or instead of its served columns.
ROUTE_EXTRAS = {
    "Project": set(),
    "Build": {"runnable", "reused", "position"},
    "Version": {"files", "build"},
    "ProjectRun": set(),
}
DETAIL_EXTRAS = ["twenty_sim", "messages", "package", "file_list", "builds", "runs"]


def _served(record: Any) -> list[str]:
    return [f for f in column_names(record) if record.__dataclass_fields__[f].metadata["api"]]


def _shape(db: Path) -> dict[str, Any]:
    """Each table's columns (name, type, not null, default, key), indexes and foreign keys."""
    with sqlite3.connect(db) as c:
        out: dict[str, Any] = {}
        for table in TABLES:
            indexes = sorted(
                (r[2], r[3], tuple(i[2] for i in c.execute(f"PRAGMA index_info('{r[1]}')")))
                for r in c.execute(f"PRAGMA index_list({table})")
            )
            out[table] = (
                [tuple(r[1:]) for r in c.execute(f"PRAGMA table_info({table})")],
                indexes,
                [tuple(r[2:]) for r in c.execute(f"PRAGMA foreign_key_list({table})")],
            )
        out["index names"] = sorted(
            r[0] for r in c.execute("SELECT name FROM sqlite_master WHERE type='index' AND sql IS NOT NULL")
        )
        return out


def test_sql_tables_are_the_definition(tmp_path: Path) -> None:
    ProjectStore(tmp_path / "projects.sqlite3").close()
    with sqlite3.connect(tmp_path / "projects.sqlite3") as c:
        for table, record in TABLES.items():
            assert [r[1] for r in c.execute(f"PRAGMA table_info({table})")] == column_names(record), table
    # ... and the same tables, keys, indexes and foreign keys as the SQL written out before
    with sqlite3.connect(tmp_path / "old.sqlite3") as c:
        c.executescript(FIRST_RELEASE)
    assert _shape(tmp_path / "projects.sqlite3") == _shape(tmp_path / "old.sqlite3")


def test_a_first_release_database_reads_as_the_records(tmp_path: Path) -> None:
    with sqlite3.connect(tmp_path / "projects.sqlite3") as c:
        c.executescript(FIRST_RELEASE)
    store = ProjectStore(tmp_path / "projects.sqlite3")
    try:
        project = store.project(1)
        assert project is not None and project.folder == "f00d" and project.origin == "upload"
        build = store.build(1)
        assert build is not None and build.details == {"cycle_freq": 1000} and build.status == "ok"
        version = store.version(1, 1)
        assert version is not None and version.files == {"src/main.cpp": "00"}
        assert store.runs_of(1) == [{"run_id": 7, "build_id": 1}]
        link = store.run_link(7)
        assert link is not None and (link.project_id, link.owner) == (1, "ann")
        # what the routes serve of a row is what its API model declares
        assert list(project.as_dict()) == _served(ProjectRow)
        assert list(build.as_dict()) == [*_served(BuildRow), "runnable"]
        assert version.as_dict()["files"] == 1
    finally:
        store.close()


def test_api_models_are_the_definition(tmp_path: Path) -> None:
    from xrflab.server.app import create_app
    from xrflab.server.http.editor import Version
    from xrflab.server.http.projects import Build, Project, ProjectDetail, ProjectRun
    from xrflab.server.settings import Settings

    models = {"Project": Project, "Build": Build, "Version": Version, "ProjectRun": ProjectRun}
    records = {"Project": ProjectRow, "Build": BuildRow, "Version": VersionRow, "ProjectRun": RunLinkRow}
    for name, model in models.items():
        assert set(model.model_fields) == set(_served(records[name])) | ROUTE_EXTRAS[name], name
    assert list(Project.model_fields) == _served(ProjectRow)  # in the definition's order
    assert list(ProjectDetail.model_fields) == [*_served(ProjectRow), *DETAIL_EXTRAS]
    assert not {"folder", "log_path", "executable"} & {f for m in models.values() for f in m.model_fields}

    # what /openapi.json publishes, the descriptions included
    schemas = create_app(Settings(data_dir=tmp_path / "data")).openapi()["components"]["schemas"]
    for name, model in {**models, "ProjectDetail": ProjectDetail}.items():
        assert list(schemas[name]["properties"]) == list(model.model_fields), name
    assert schemas["Build"]["properties"]["status"]["enum"] == ["queued", "building", "ok", "failed"]
    assert schemas["Version"]["properties"]["files"]["type"] == "integer"
    assert "assignment:<id>" in schemas["Project"]["properties"]["origin"]["description"]
    builds = schemas["ProjectDetail"]["properties"]["builds"]
    assert builds["items"] == {"$ref": "#/components/schemas/Build"}


def test_the_rows_need_only_the_standard_library() -> None:
    """The build sandbox runs projects/builder.py, which reads these rows, with a system Python
    that has no pydantic: the models are made only when a route asks for them."""
    code = "import sys, xrflab.projects.builder, xrflab.projects.store; assert 'pydantic' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)
