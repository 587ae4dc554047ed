"""The run record has one definition (runs.RunRow): the SQL table, the API's RunRecord and the
log listing's RunLogRecord are made from it, so they cannot disagree (they had: the API left
out the log counts, the log listing had its own copy)."""

from __future__ import annotations

import sqlite3
from dataclasses import fields
from pathlib import Path

from xrflab.server.runs.store import RunRecord, RunRow, RunStore

DEFINITION = [f.name for f in fields(RunRow)]
LOG_LISTING_LEAVES_OUT = {"shm", "pid", "exit_code", "exit_signal", "run_dir"}

# The table as the first release created it: an appliance upgraded from it keeps its runs.
FIRST_RELEASE = """
CREATE TABLE runs (
    id INTEGER PRIMARY KEY AUTOINCREMENT, build TEXT NOT NULL, program TEXT NOT NULL DEFAULT '',
    sim TEXT NOT NULL DEFAULT '', shm TEXT NOT NULL DEFAULT '', pid INTEGER, started REAL NOT NULL,
    ended REAL, status TEXT NOT NULL, crashed INTEGER NOT NULL DEFAULT 0,
    crash_reason TEXT NOT NULL DEFAULT '', exit_code INTEGER, exit_signal INTEGER,
    state TEXT NOT NULL DEFAULT '', cycles INTEGER NOT NULL DEFAULT 0, misses INTEGER NOT NULL DEFAULT 0,
    cycle_freq INTEGER NOT NULL DEFAULT 0, run_dir TEXT NOT NULL DEFAULT '', message TEXT NOT NULL DEFAULT ''
);
INSERT INTO runs (build, started, status, cycles) VALUES ('relbot', 1.0, 'ended', 7);
"""


def _columns(db: Path) -> list[str]:
    with sqlite3.connect(db) as c:
        return [r[1] for r in c.execute("PRAGMA table_info(runs)")]


def test_sql_columns_are_the_definition(tmp_path: Path) -> None:
    store = RunStore(tmp_path / "runs.db")
    store.close()
    assert _columns(tmp_path / "runs.db") == DEFINITION


def test_a_first_release_database_gains_every_later_field(tmp_path: Path) -> None:
    with sqlite3.connect(tmp_path / "runs.db") as c:
        c.executescript(FIRST_RELEASE)
    store = RunStore(tmp_path / "runs.db")
    try:
        row = store.get(1)
        assert row is not None and row.cycles == 7 and row.owner == "" and row.end_reason == ""
    finally:
        store.close()
    assert sorted(_columns(tmp_path / "runs.db")) == sorted(DEFINITION)


def test_api_models_are_the_definition(tmp_path: Path) -> None:
    from xrflab.server.app import create_app
    from xrflab.server.http.logs import RunLogRecord
    from xrflab.server.settings import Settings

    assert list(RunRecord.model_fields) == DEFINITION
    assert set(RunLogRecord.model_fields) == (set(DEFINITION) - LOG_LISTING_LEAVES_OUT) | {"duration_s", "live"}
    # what /openapi.json publishes, the descriptions included
    schemas = create_app(Settings(data_dir=tmp_path / "data")).openapi()["components"]["schemas"]
    assert list(schemas["RunRecord"]["properties"]) == DEFINITION
    assert set(schemas["RunLogRecord"]["properties"]) == set(RunLogRecord.model_fields)
    assert "cycle_limit" in schemas["RunRecord"]["properties"]["end_reason"]["description"]
    assert schemas["RunRecord"]["properties"]["status"]["enum"] == ["starting", "running", "ended", "crashed", "failed"]
