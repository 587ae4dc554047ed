"""Small things a first afternoon tripped over (issue 31, bug 8), without a browser: the lease's
re-queue of a student taken over from and its "who paused your run" event (in-process), the run
user's own description (root: a real system user), and a clean stop leaving no SQLite -wal/-shm
(a real appliance process)."""

from __future__ import annotations

import os
import pwd
import subprocess
import uuid
from pathlib import Path
from typing import Any

import pytest

from xrflab.server.security.accounts import User
from xrflab.server.security.lease import Lease
from xrflab.server.ws.messages import LeaseMessage

ANN = User(1, "ann", "student")
BOB = User(2, "bob", "student")
CAT = User(3, "cat", "student")
EVE = User(4, "eve", "educator")
ZED = User(5, "zed", "educator")


def _bench() -> tuple[Lease, list[LeaseMessage], list[tuple[str | None, str]]]:
    messages: list[LeaseMessage] = []
    audit: list[tuple[str | None, str]] = []

    def record(actor: User | None, action: str, detail: dict[str, Any]) -> None:
        audit.append((actor.username if actor else None, action))

    return Lease(60.0, messages.append, record), messages, audit


def test_a_student_taken_over_from_is_first_in_the_queue_and_gets_the_bench_back() -> None:
    lease, messages, _ = _bench()
    lease.take(ANN)
    lease.enqueue(CAT)
    lease.take(EVE)  # the educator's take-over
    assert lease.holder is not None and lease.holder.user.username == "eve"
    assert [u.username for u in lease.queue] == ["ann", "cat"]  # ann ahead of cat, who queued earlier
    told = messages[-1]
    assert told.event == "takeover" and told.previous is not None and told.previous.username == "ann"
    assert told.reason is not None and "ann is first in the queue" in told.reason
    assert [w.username for w in told.queue] == ["ann", "cat"]
    lease.release(EVE)
    assert lease.holder is not None and lease.holder.user.username == "ann"
    assert messages[-1].event == "handover" and [u.username for u in lease.queue] == ["cat"]


def test_an_educator_taken_over_from_does_not_queue() -> None:
    lease, messages, _ = _bench()
    lease.take(EVE)
    lease.take(ZED)
    assert lease.queue == [] and messages[-1].event == "takeover" and messages[-1].reason is None


def test_the_holder_hears_who_paused_or_stopped_the_run() -> None:
    lease, messages, audit = _bench()
    lease.take(ANN)
    n, recorded = len(messages), len(audit)
    lease.intervened(ANN, "pause")  # the holder's own pause: nothing to tell
    assert len(messages) == n
    lease.intervened(BOB, "pause")
    told = messages[-1]
    assert told.event == "intervention" and told.command == "pause"
    assert told.by is not None and told.by.username == "bob"
    assert told.holder is not None and told.holder.username == "ann"
    lease.intervened(EVE, "stop")
    assert messages[-1].command == "stop" and messages[-1].by.username == "eve"  # type: ignore[union-attr]
    assert len(audit) == recorded  # the command is audited by the route, not twice
    lease.release(ANN)
    n = len(messages)
    lease.intervened(BOB, "stop")  # nobody holds the bench: nobody to tell
    assert len(messages) == n


def test_the_run_user_gets_its_own_description() -> None:
    """xrf-run used to be created as "XRF Lab student builds", the build user's description; an
    account made so by an earlier appliance is corrected, an administrator's own text kept."""
    if os.geteuid() != 0:
        pytest.skip("creating a system user needs root")
    from xrflab.projects.build_user import BUILD_USER_COMMENT, RUN_USER_COMMENT
    from xrflab.server.runs.guest_spawn import identity

    name = f"xrft-{uuid.uuid4().hex[:8]}"
    try:
        ident = identity(name)
        entry = pwd.getpwnam(name)
        assert ident.uid == entry.pw_uid and entry.pw_gecos == RUN_USER_COMMENT
        assert RUN_USER_COMMENT != BUILD_USER_COMMENT
        subprocess.run(["usermod", "--comment", BUILD_USER_COMMENT, name], check=True)
        identity(name)
        assert pwd.getpwnam(name).pw_gecos == RUN_USER_COMMENT
        subprocess.run(["usermod", "--comment", "kept by the administrator", name], check=True)
        identity(name)
        assert pwd.getpwnam(name).pw_gecos == "kept by the administrator"
    finally:
        subprocess.run(["userdel", name], capture_output=True)
        subprocess.run(["groupdel", name], capture_output=True)


def test_a_clean_stop_leaves_no_sqlite_wal_or_shm(tmp_path: Path) -> None:
    from xrf_testing.harness import shared_builds_root, start_server, stop_server

    data = tmp_path / "data"
    server = start_server(data, shared_builds_root())
    try:
        # Every database written: projects (a project from a template), runs, accounts, audit.
        r = server.http.post("/api/projects/from-template", json={"template": "base", "name": "wal_check"})
        assert r.status_code == 201, r.text
        assert server.http.get("/api/runs").status_code == 200
        server.create_user("walter", "student")
        databases = sorted(p.name for p in data.glob("*.sqlite3"))
        assert {"projects.sqlite3", "runs.sqlite3", "accounts.sqlite3", "audit.sqlite3"} <= set(databases)
        assert list(data.glob("*.sqlite3-wal")), "expected write-ahead logs while running"
    finally:
        stop_server(server)
    left = sorted(p.name for p in data.iterdir() if p.name.endswith(("-wal", "-shm")))
    assert left == [], left


def test_reset_zeroes_a_bounded_string_setpoint_too() -> None:
    """With a std_msgs/Header in Ros2Xeno the setpoints hold a string (header.frame_id): reset's
    zeros must encode, or none of the setpoints start over."""
    from types import SimpleNamespace

    from xrflab.msgdef import Codec
    from xrflab.server.http.runs import _zero_setpoints_after_reset

    codec = Codec("std_msgs/Header header\nfloat64 speed\nint32[2] pair\nbool on")
    written: list[bytes] = []
    run = SimpleNamespace(
        setpoint={"header.frame_id": "base", "header.stamp.sec": 4, "speed": 1.5, "pair": [1, 2], "on": True}
    )

    class Sup:
        current = run

        def setpoint(self, fields: dict[str, Any]) -> dict[str, Any]:
            written.append(codec.encode({**run.setpoint, **fields}))  # as control.setpoint: ValueError if bad
            run.setpoint = {**run.setpoint, **fields}
            return run.setpoint

    _zero_setpoints_after_reset(Sup(), "reset", True)  # type: ignore[arg-type]
    assert written and codec.decode(written[-1]) == {
        **codec.decode(codec.encode({})),
        "header.frame_id": "",
    }
    assert run.setpoint == {"header.frame_id": "", "header.stamp.sec": 0, "speed": 0, "pair": [0, 0], "on": False}
