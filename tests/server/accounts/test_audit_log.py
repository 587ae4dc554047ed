"""The audit trail's store in-process (server/security/audit.py's AuditLog): rows outlive their
account, the action filter is a dotted prefix (and LIKE's wildcards in it are literal), the newest
first with paging, and the CSV export cannot carry a spreadsheet formula."""

from __future__ import annotations

import csv
import io
import stat
from pathlib import Path

import pytest

from xrflab.server.security.accounts import User
from xrflab.server.security.audit import AuditLog

ANN = User(1, "ann", "student")
EVE = User(2, "eve", "educator")


@pytest.fixture
def log(tmp_path: Path):
    a = AuditLog(tmp_path / "data" / "audit.sqlite3")
    yield a
    a.close()


def test_rows_keep_who_did_it_and_the_file_is_private(log: AuditLog, tmp_path: Path) -> None:
    log.record(ANN, "lease.take", {"queue": []}, address="10.0.0.5")
    log.record(None, "lease.released", {"reason": "idle"})
    log.record(EVE, "user.disable", "ann")  # a detail that is not a dict is wrapped
    rows = log.query()
    assert [r["action"] for r in rows] == ["user.disable", "lease.released", "lease.take"]  # newest first
    assert rows[2]["username"] == "ann" and rows[2]["role"] == "student" and rows[2]["address"] == "10.0.0.5"
    assert rows[1]["user_id"] is None and rows[1]["username"] == ""  # the appliance itself
    assert rows[0]["detail"] == {"detail": "ann"}
    assert stat.S_IMODE((tmp_path / "data" / "audit.sqlite3").stat().st_mode) == 0o600


def test_filters_prefix_user_time_and_paging(log: AuditLog) -> None:
    for action in ("lease.take", "lease.release", "leasehold.x", "lease_x.y", "run.start"):
        log.record(ANN, action)
    log.record(EVE, "lease.takeover")
    assert {r["action"] for r in log.query(action="lease")} == {"lease.take", "lease.release", "lease.takeover"}
    assert [r["action"] for r in log.query(action="lease_x")] == ["lease_x.y"]  # "_" is not a wildcard
    assert log.query(action="lease.take")[0]["action"] == "lease.take"  # exact names match too
    assert [r["username"] for r in log.query(username=" EVE ")] == ["eve"]
    newest = log.query()[0]["t"]
    assert [r["action"] for r in log.query(since=newest)] == ["lease.takeover"]
    assert len(log.query(until=newest - 3600)) == 0
    page = [r["id"] for r in log.query(limit=2, offset=1)]
    assert page == [r["id"] for r in log.query()][1:3]


def test_oversized_text_is_cut_not_refused(log: AuditLog) -> None:
    log.record(ANN, "x" * 500, {"blob": "y" * 50_000}, address="z" * 500)
    row = log.query()[0]
    assert len(row["action"]) == 100 and len(row["address"]) == 100
    assert isinstance(row["detail"], str) and len(row["detail"]) == 20_000  # cut JSON stays text


def test_csv_export_defuses_formulas(log: AuditLog) -> None:
    log.record(User(3, "=cmd|'/c calc'!A1", "student"), "auth.login_failed", "=HYPERLINK(1)")
    log.record(ANN, "run.start", {"build": "relbot"})
    lines = list(csv.reader(io.StringIO(AuditLog.to_csv(log.query()))))
    assert lines[0] == ["id", "time_utc", "username", "role", "action", "detail", "address"]
    by_action = {row[4]: row for row in lines[1:]}
    assert by_action["run.start"][5] == '{"build":"relbot"}'
    assert not by_action["auth.login_failed"][5].startswith("=")
