"""Run records in SQLite: which build ran, on which bench, how it ended.

Writes are a handful per run (start, end), so the stdlib sqlite3 module is used synchronously
from the event loop: each statement is sub-millisecond and a thread hop would cost more than it
saves. One connection, autocommit, WAL so a reader (a second `xrf` process) never blocks us.
"""

from __future__ import annotations

import sqlite3
import time
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from .private_files import private_db

_SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    build TEXT NOT NULL,
    program TEXT NOT NULL DEFAULT '',
    sim TEXT NOT NULL DEFAULT '',
    shm TEXT NOT NULL DEFAULT '',
    pid INTEGER,
    started REAL NOT NULL,
    ended REAL,
    status TEXT NOT NULL,          -- starting | running | ended | crashed | failed
    crashed INTEGER NOT NULL DEFAULT 0,
    crash_reason TEXT NOT NULL DEFAULT '',   -- signal | exit | hang | ''
    exit_code INTEGER,
    exit_signal INTEGER,
    state TEXT NOT NULL DEFAULT '',  -- last loop state seen
    cycles INTEGER NOT NULL DEFAULT 0,
    misses INTEGER NOT NULL DEFAULT 0,
    cycle_freq INTEGER NOT NULL DEFAULT 0,
    run_dir TEXT NOT NULL DEFAULT '',
    message TEXT NOT NULL DEFAULT ''
);
"""

# Columns added after the first release: (name, declaration). Added with ALTER TABLE when an
# older database lacks them, so existing run records survive an upgrade.
_ADDED_COLUMNS = (
    ("owner", "TEXT NOT NULL DEFAULT ''"),        # user who started the run (issue 7 fills it)
    ("log_records", "INTEGER NOT NULL DEFAULT 0"),  # records in the run's log files
    ("log_lost", "INTEGER NOT NULL DEFAULT 0"),     # ring drops + records drained after a write failure
    ("log_note", "TEXT NOT NULL DEFAULT ''"),       # why logging stopped (disk full, ...), '' = it did not
    ("end_reason", "TEXT NOT NULL DEFAULT ''"),     # END_REASONS: how the run ended, '' while it runs
)

# Every way a run can end: the `end_reason` of its record (and of its alarm), one name each.
END_REASONS: dict[str, str] = {
    "stopped": "stopped by its owner",
    "stopped_by_other": "stopped by someone else (an educator, the self-check)",
    "quit": "the loop handled a quit command",
    "cycle_limit": "the cycle limit was reached",
    "signal_stop": "the loop took its safe stop on SIGINT/SIGTERM",
    "returned": "the program left its loop and ended",
    "self_exit": "the controller ended by itself without stop or quit",
    "crash": "the process crashed (a signal or a non-zero exit status)",
    "hang": "the loop stopped cycling and was killed",
    "appliance_restart": "the appliance died during the run; its restart ended it",
    "shutdown": "the appliance shut down",
    "disk": "the run folder went over its disk limit",
    "start_failed": "the controller did not start",
}


@dataclass
class RunRow:
    id: int
    build: str
    program: str
    sim: str
    shm: str
    pid: int | None
    started: float
    ended: float | None
    status: str
    crashed: bool
    crash_reason: str
    exit_code: int | None
    exit_signal: int | None
    state: str
    cycles: int
    misses: int
    cycle_freq: int
    run_dir: str
    message: str
    owner: str = ""
    log_records: int = 0
    log_lost: int = 0
    log_note: str = ""
    end_reason: str = ""

    def as_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


_COLUMNS = [f.name for f in fields(RunRow)]


class RunStore:
    def __init__(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        private_db(path)  # 0600 before SQLite opens it: its WAL/SHM take the same mode
        self._db = sqlite3.connect(str(path), isolation_level=None, check_same_thread=False)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.executescript(_SCHEMA)
        have = {r[1] for r in self._db.execute("PRAGMA table_info(runs)")}
        for name, decl in _ADDED_COLUMNS:
            if name not in have:
                self._db.execute(f"ALTER TABLE runs ADD COLUMN {name} {decl}")
        # A previous appliance process that died mid-run left rows 'running': they did not end
        # cleanly and nobody watched them end, so say so rather than show them as live.
        self.orphans: list[RunRow] = [
            _row(r) for r in self._db.execute(
                f"SELECT {', '.join(_COLUMNS)} FROM runs WHERE status IN ('starting', 'running')"
            ).fetchall()
        ]
        self._db.execute(
            "UPDATE runs SET status='crashed', crashed=1, crash_reason='appliance', "
            "message='the appliance stopped while this run was live', ended=COALESCE(ended, ?) "
            "WHERE status IN ('starting', 'running')",
            (time.time(),),
        )

    def close(self) -> None:
        self._db.close()

    def create(self, build: str, sim: str, shm: str, run_dir: str) -> RunRow:
        cur = self._db.execute(
            "INSERT INTO runs (build, sim, shm, started, status, run_dir) VALUES (?, ?, ?, ?, 'starting', ?)",
            (build, sim, shm, time.time(), run_dir),
        )
        row = self.get(int(cur.lastrowid or 0))
        assert row is not None
        return row

    def update(self, run_id: int, **values: Any) -> RunRow:
        unknown = set(values) - set(_COLUMNS)
        if unknown:
            raise KeyError(f"unknown run columns {sorted(unknown)}")
        if values:
            assignments = ", ".join(f"{k}=?" for k in values)
            self._db.execute(f"UPDATE runs SET {assignments} WHERE id=?", (*values.values(), run_id))
        row = self.get(run_id)
        if row is None:
            raise KeyError(run_id)
        return row

    def get(self, run_id: int) -> RunRow | None:
        if not -(2**63) <= run_id < 2**63:  # beyond SQLite's INTEGER (a guessed or fuzzed id): no such run
            return None
        cur = self._db.execute(f"SELECT {', '.join(_COLUMNS)} FROM runs WHERE id=?", (run_id,))
        r = cur.fetchone()
        return _row(r) if r else None

    def list(self, limit: int = 100, owner: str | None = None) -> list[RunRow]:
        """Newest first; `owner`: only that user's runs (compared as auth.owns does)."""
        if owner is None:
            cur = self._db.execute(f"SELECT {', '.join(_COLUMNS)} FROM runs ORDER BY id DESC LIMIT ?", (limit,))
        else:
            cur = self._db.execute(f"SELECT {', '.join(_COLUMNS)} FROM runs WHERE lower(trim(owner)) = ? "
                                   "ORDER BY id DESC LIMIT ?", (owner.strip().lower(), limit))
        return [_row(r) for r in cur.fetchall()]


def _row(r: tuple[Any, ...]) -> RunRow:
    d = dict(zip(_COLUMNS, r))
    d["crashed"] = bool(d["crashed"])
    return RunRow(**d)
