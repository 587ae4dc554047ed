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
from typing import Any, Literal

from pydantic import BaseModel

from ...private_files import private_db
from ...records import add_missing_columns, api_model, column, column_names, create_table, from_sql, to_sql
from .watch_record import SafeOutcome

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
    "appliance_gone": "the appliance died during the run; the run's xrf-watch stopped the loop and made it safe",
    "shutdown": "the appliance shut down",
    "disk": "the run folder went over its disk limit",
    "corrupt_channel": "the controller broke the rules of its shared memory (sizes, counters, layout)",
    "memory": "the run went over its memory limit (its processes and its /dev/shm together)",
    "pids": "the run went over its process limit",
    "cpu": "the run went over its CPU limit (real-time time without blocking, or CPU time)",
    "start_failed": "the controller did not start",
}


RunStatus = Literal["starting", "running", "ended", "crashed", "failed"]


def _col(sql: str, doc: str = "", added: bool = False, **default: Any) -> Any:
    """A run record field (records.column): its SQLite declaration, its description in the API,
    and whether it came after the first release (then an older database gets it with ALTER
    TABLE, so existing run records survive an upgrade)."""
    return column(sql, doc, added=added, **default)


@dataclass
class RunRow:
    """The run record: THE definition. The SQL table (`schema()`), the API's RunRecord
    (`record_model()`) and the log listing's record (routes_logs.RunLogRecord) derive from it; a
    field added here is in all three (tests/server/test_run_record.py)."""

    id: int = _col("INTEGER PRIMARY KEY AUTOINCREMENT")
    build: str = _col("TEXT NOT NULL", "the build that ran (GET /api/builds)")
    program: str = _col("TEXT NOT NULL DEFAULT ''", "the controller's program name")
    sim: str = _col("TEXT NOT NULL DEFAULT ''", "the simulated plant")
    shm: str = _col("TEXT NOT NULL DEFAULT ''", "the run's shared memory below /dev/shm")
    pid: int | None = _col("INTEGER", "the controller's process id")
    started: float = _col("REAL NOT NULL", "Unix time")
    ended: float | None = _col("REAL", "Unix time; null while it runs")
    status: RunStatus = _col("TEXT NOT NULL")
    crashed: bool = _col("INTEGER NOT NULL DEFAULT 0")
    crash_reason: str = _col(
        "TEXT NOT NULL DEFAULT ''", "signal | exit | hang | self_exit | appliance, empty if not crashed"
    )
    exit_code: int | None = _col("INTEGER")
    exit_signal: int | None = _col("INTEGER")
    state: str = _col("TEXT NOT NULL DEFAULT ''", "last loop state seen")
    cycles: int = _col("INTEGER NOT NULL DEFAULT 0")
    misses: int = _col("INTEGER NOT NULL DEFAULT 0")
    cycle_freq: int = _col("INTEGER NOT NULL DEFAULT 0")
    run_dir: str = _col("TEXT NOT NULL DEFAULT ''")
    message: str = _col("TEXT NOT NULL DEFAULT ''")
    owner: str = _col(
        "TEXT NOT NULL DEFAULT ''",
        "username of who started the run ('' = an educator before accounts)",
        added=True,
        default="",
    )
    log_records: int = _col(
        "INTEGER NOT NULL DEFAULT 0", "records written to the run's log files", added=True, default=0
    )
    log_lost: int = _col(
        "INTEGER NOT NULL DEFAULT 0",
        "records lost: ring full (writer stalled) or not written after a disk error",
        added=True,
        default=0,
    )
    log_note: str = _col(
        "TEXT NOT NULL DEFAULT ''", "why logging stopped (disk full, ...); '' normally", added=True, default=""
    )
    end_reason: str = _col(
        "TEXT NOT NULL DEFAULT ''",
        "how the run ended: " + ", ".join(f"{k} ({v})" for k, v in END_REASONS.items()) + "; empty while it runs",
        added=True,
        default="",
    )
    safe_outcome: SafeOutcome | None = _col(
        "TEXT NOT NULL DEFAULT ''",
        "a `hold` run that failed: what the safety watcher did (by 'watcher': the appliance's own, when the loop "
        "failed; by 'xrf-watch': the run's own, while the appliance was gone, from its record in the run folder, "
        "checked): the largest joint drop, the time to rest; null otherwise",
        added=True,
        json_text=True,
        default=None,
    )

    def as_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


_COLUMNS = column_names(RunRow)


def schema() -> str:
    """CREATE TABLE for the run records, from RunRow."""
    return create_table("runs", RunRow)


def record_model(
    name: str = "RunRecord", exclude: frozenset[str] = frozenset(), **extra: tuple[Any, Any]
) -> type[BaseModel]:
    """The API model of a run record, from RunRow: every field (but `exclude`), typed and
    described as RunRow says, then `extra` (name=(type, pydantic Field)) that the route adds."""
    return api_model(RunRow, name, extra, exclude)


# What the API answers for a run (GET /api/runs, POST /api/runs, ...).
RunRecord = record_model()


class RunStore:
    def __init__(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        private_db(path)  # 0600 before SQLite opens it: its WAL/SHM take the same mode
        self._db = sqlite3.connect(str(path), isolation_level=None, check_same_thread=False)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.executescript(schema())
        add_missing_columns(self._db, "runs", RunRow)
        # A previous appliance process that died mid-run left rows 'running': they did not end
        # cleanly and nobody watched them end, so say so rather than show them as live.
        self.orphans: list[RunRow] = [
            _row(r)
            for r in self._db.execute(
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
        values = to_sql(RunRow, values)  # JSON columns (safe_outcome) as text
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
            cur = self._db.execute(
                f"SELECT {', '.join(_COLUMNS)} FROM runs WHERE lower(trim(owner)) = ? ORDER BY id DESC LIMIT ?",
                (owner.strip().lower(), limit),
            )
        return [_row(r) for r in cur.fetchall()]


def _row(r: tuple[Any, ...]) -> RunRow:
    return from_sql(RunRow, r)  # crashed: SQLite's 0/1 as the bool RunRow declares
