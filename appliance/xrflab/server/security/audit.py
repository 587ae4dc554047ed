"""The audit trail (<data dir>/audit.sqlite3): who did what when. Commands, runs, uploads, builds,
self-checks, lease changes, logins and account changes.

Other modules call ``audit.record(user, "build.start", {"project": 3})``: one row with the time,
the user (id, name and role copied, so the row outlives the account) and a JSON detail. Actions
are dotted names, the first part the area: ``auth``, ``user``, ``lease``, ``run``, ``command``,
``project``, ``build``, ``selfcheck``.
"""

from __future__ import annotations

import csv
import io
import json
import sqlite3
import time
from pathlib import Path
from typing import Any

from ...private_files import private_db
from .accounts import User

_SCHEMA = """
CREATE TABLE IF NOT EXISTS audit (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    t REAL NOT NULL,
    user_id INTEGER,
    username TEXT NOT NULL DEFAULT '',
    role TEXT NOT NULL DEFAULT '',
    action TEXT NOT NULL,
    detail TEXT NOT NULL DEFAULT '{}',
    address TEXT NOT NULL DEFAULT ''
);
CREATE INDEX IF NOT EXISTS audit_t ON audit (t);
CREATE INDEX IF NOT EXISTS audit_user ON audit (username);
"""

COLUMNS = ("id", "t", "user_id", "username", "role", "action", "detail", "address")


class AuditLog:
    def __init__(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        private_db(path)  # 0600 before SQLite opens it: its WAL/SHM take the same mode
        self._db = sqlite3.connect(str(path), isolation_level=None, check_same_thread=False)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.executescript(_SCHEMA)

    def close(self) -> None:
        self._db.close()

    def record(self, user: User | None, action: str, detail: Any = None, address: str = "") -> None:
        if detail is None:
            detail = {}
        elif not isinstance(detail, dict):
            detail = {"detail": detail}
        self._db.execute(
            "INSERT INTO audit (t, user_id, username, role, action, detail, address) VALUES (?, ?, ?, ?, ?, ?, ?)",
            (
                time.time(),
                user.id if user else None,
                user.username if user else "",
                user.role if user else "",
                action[:100],
                json.dumps(detail, default=str, separators=(",", ":"))[:20000],
                address[:100],
            ),
        )

    def query(
        self,
        username: str | None = None,
        action: str | None = None,
        since: float | None = None,
        until: float | None = None,
        limit: int = 500,
        offset: int = 0,
    ) -> list[dict[str, Any]]:
        where: list[str] = []
        args: list[str | float] = []
        if username:
            where.append("username = ?")
            args.append(username.strip().lower())
        if action:
            # a prefix: "lease" matches lease.take, lease.release, ...
            where.append("(action = ? OR action LIKE ? ESCAPE '\\')")
            escaped = action.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")
            args += [action, escaped + ".%"]
        if since is not None:
            where.append("t >= ?")
            args.append(since)
        if until is not None:
            where.append("t <= ?")
            args.append(until)
        sql = f"SELECT {', '.join(COLUMNS)} FROM audit"
        if where:
            sql += " WHERE " + " AND ".join(where)
        sql += " ORDER BY id DESC LIMIT ? OFFSET ?"
        rows = []
        for r in self._db.execute(sql, (*args, limit, offset)):
            d = dict(zip(COLUMNS, r))
            try:
                d["detail"] = json.loads(d["detail"])
            except ValueError:
                pass
            rows.append(d)
        return rows

    @staticmethod
    def to_csv(rows: list[dict[str, Any]]) -> str:
        out = io.StringIO()
        w = csv.writer(out)
        w.writerow(["id", "time_utc", "username", "role", "action", "detail", "address"])
        for r in rows:
            when = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(r["t"]))
            detail = json.dumps(r["detail"], separators=(",", ":")) if not isinstance(r["detail"], str) else r["detail"]
            w.writerow([r["id"], when, r["username"], r["role"], r["action"], _cell(detail), r["address"]])
        return out.getvalue()


def _cell(text: str) -> str:
    """No formula injection when the export is opened in a spreadsheet."""
    return "'" + text if text[:1] in ("=", "+", "-", "@", "\t", "\r") else text


# The appliance's log, set while the app runs (one app per process). record() before that, or in
# a process without an appliance, is a no-op: auditing never breaks the action being audited.
_current: AuditLog | None = None


def use(log: AuditLog | None) -> None:
    global _current
    _current = log


def record(user: User | None, action: str, detail: Any = None, address: str = "") -> None:
    if _current is not None:
        try:
            _current.record(user, action, detail, address)
        except sqlite3.Error:
            pass
