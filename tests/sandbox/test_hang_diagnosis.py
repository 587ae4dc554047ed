"""A hang's diagnosis tells a controller's infinite loop from a loop blocked in the kernel.

tests/fixtures/hang_controller (over the base template), uploaded, built and run through the real
appliance, hangs on purpose once INITIALISED: a busy loop in user code, or a read on a pipe nobody
writes. The safety watcher declares the hang, and before the kill records where the loop's
threads were (rt_core/src/watch.c ``diagnose``, server/runs/hang_diag.py): the run's end note
says it in words, ``hang-diagnosis.json`` in the run's folder has the details.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from xrf_testing.harness import UNCONFINED_UNLESS_ROOT, Server, shared_builds_root, start_server, stop_server, wait_for
from xrf_testing.hostile import project_files
from xrf_testing.projects_support import targz, upload_and_build
from xrflab.server.runs import hang_diag

REPO = Path(__file__).resolve().parents[2]
FIXTURE = REPO / "tests" / "fixtures" / "hang_controller"
BASE = REPO / "student_projects" / "templates" / "base"
SPIN, BLOCK = 1, 2


pytestmark = pytest.mark.rt_hog  # a controller hung in a busy loop at real-time priority


@pytest.fixture(scope="module")
def server(data_dir: Path) -> Iterator[Server]:
    """As the sandbox's, but a normal user's appliance may run the controller unconfined (it
    cannot confine it fully on a machine like the CI's: docs/developers/testing.md)."""
    s = start_server(data_dir, shared_builds_root(), allow_unconfined=UNCONFINED_UNLESS_ROOT)
    yield s
    stop_server(s)


@pytest.fixture(scope="module")
def hanging(server: Server) -> tuple[httpx.Client, Any, int, int]:
    """A student holding the bench, the hanging controller built: (client, her WebSockets,
    project, build)."""
    http, ws = server.login("hana", server.create_user("hana"))
    files = {**project_files(BASE), **project_files(FIXTURE)}
    pid, bid = upload_and_build(http, targz(files, "hang"), "hang.tar.gz")
    assert http.post("/api/lease/take").status_code == 200
    return http, ws, pid, bid


def hang_run(server: Server, hanging: tuple[httpx.Client, Any, int, int], mode: int) -> tuple[dict[str, Any], dict]:
    """Run the controller in `mode` until it hangs: (the run's final record, its diagnosis file)."""
    http, ws_of, pid, bid = hanging
    server.stop_run()
    r = http.post(f"/api/projects/{pid}/builds/{bid}/run", json={"max_cycles": 2_000_000_000 + mode}, timeout=60)
    assert r.status_code == 201, r.text
    run = r.json()["run"]
    with ws_of() as ws:
        ws.wait_state("IDLE", 60)
        assert ws.command("initialise")["accepted"]
        alarm = ws.wait_type("alarm", timeout=30, kind="hang", run_id=run["id"])

    def final() -> dict[str, Any] | None:
        row = server.http.get(f"/api/runs/{run['id']}").json()
        return row if row["status"] in ("ended", "crashed", "failed") else None

    row = wait_for(final, 30, f"run {run['id']} to end")
    assert row["end_reason"] == "hang", row
    assert "hang diagnosis:" in row["message"] and "hang diagnosis:" in alarm["message"], row
    path = server.data_dir / "runs" / str(run["id"]) / hang_diag.RECORD
    assert path.is_file(), f"no {hang_diag.RECORD} in the run's folder: {row['message']}"
    return row, json.loads(path.read_text())


def loop_thread(diag: dict) -> dict:
    t = hang_diag.loop_thread(diag["threads"], diag["pid"])
    assert t is not None, diag
    return t


def test_a_busy_loop_in_user_code_is_told_as_such(server: Server, hanging: Any) -> None:
    row, diag = hang_run(server, hanging, SPIN)
    t = loop_thread(diag)
    # On its CPU (or preempted there) in user code: no system call, no wait channel. (syscall and
    # wchan need ptrace access to the guest: a root appliance has it, a normal user's may not.)
    assert t["state"] == "R", diag
    assert t.get("syscall", "user") in ("running", "user"), diag
    assert not t.get("wchan"), diag
    # "computing": a normal user's appliance cannot read where (user code or the kernel).
    assert any(w in row["message"] for w in ("user code", "computing", "kept off its CPU")), row["message"]
    assert "blocked" not in diag["verdict"], diag["verdict"]


def test_a_loop_blocked_in_a_system_call_is_told_as_such(server: Server, hanging: Any) -> None:
    row, diag = hang_run(server, hanging, BLOCK)
    t = loop_thread(diag)
    assert t["state"] == "S", diag
    assert t["oncpu_us"] == 0, diag  # asleep: not a microsecond on a CPU between the two looks
    if "syscall" in t:  # readable (ptrace access: a root appliance)
        assert t["syscall"] == "read" and "system call read" in row["message"], diag
    assert "blocked" in row["message"], row["message"]
    assert "user code" not in diag["verdict"], diag["verdict"]
    # The other threads are there too (the runtime's helper), each with its scheduling.
    assert len(diag["threads"]) >= 2 and all("policy" in th for th in diag["threads"]), diag


def test_what_the_guest_named_its_threads_is_bounded_and_printable() -> None:
    """The records as the watcher writes them, with a thread name a guest chose: shown cut short
    and printable, never trusted for the parse (a ')' and a newline in it)."""
    name = b"evil) R 1 2\n\x1b[31m" + b"x" * 300
    stat = b"4242 (" + name + b") S 1 4242 4242 0 -1 0 0 0 0 0" + b" 0" * 25 + b" 1 80 1\n"
    raw = b""
    for kind, data in (
        (hang_diag.lib.XRF_DIAG_STAT, stat),
        (hang_diag.lib.XRF_DIAG_SYSCALL, b"0 0x3 0x1 0x1\n"),
        (hang_diag.lib.XRF_DIAG_WCHAN, b"pipe_read"),
    ):
        raw += hang_diag._REC.pack(kind, len(data), 4242) + data
    raw += hang_diag._REC.pack(hang_diag.lib.XRF_DIAG_STAT, 5000, 4243) + b"short"  # cut off: ignored
    diag = hang_diag.parse(raw, 4242, machine="x86_64")
    (t,) = diag["threads"]
    assert len(t["name"]) <= 32 and t["name"].isprintable() and "\n" not in t["name"]
    assert t["state"] == "S" and t["syscall"] == "read" and t["policy"] == "SCHED_FIFO" and t["rt_priority"] == 80
    assert "blocked" in diag["verdict"]


def test_a_loop_kept_off_its_cpu_names_who_held_it() -> None:
    """The loop thread runnable without a tick of CPU time in the 10 ms, another program's real-time
    thread on its CPU with all of it: the verdict says so and names that thread (its name cut
    short and printable as the loop's)."""

    def stat(tid: int, name: bytes, state: bytes, cpu: int, prio: int) -> bytes:
        return (
            b"%d (" % tid + name + b") " + state + b" 1 1 1 0 -1 0 0 0 0 0" + b" 0" * 25 + b" %d %d 1\n" % (cpu, prio)
        )

    rec = hang_diag._REC.pack
    lib = hang_diag.lib
    raw = b""
    for kind, tid, data in (
        (lib.XRF_DIAG_STAT, 100, stat(100, b"relbot", b"R", 1, 80)),
        (lib.XRF_DIAG_SYSCALL, 100, b"230 0x1 0x1 0x0\n"),
        (lib.XRF_DIAG_SCHEDSTAT, 100, b"5000000 100 10\n"),
        (lib.XRF_DIAG_OTHER, 777, stat(777, b"spin\x07\nner", b"R", 1, 99)),
        (lib.XRF_DIAG_OTHER_SCHEDSTAT, 777, b"1000000 0 1\n"),
        (lib.XRF_DIAG_SCHEDSTAT2, 100, b"5000000 100 10\n"),
        (lib.XRF_DIAG_OTHER_SCHEDSTAT2, 777, b"9000000 0 1\n"),
    ):
        raw += rec(kind, len(data), tid) + data
    diag = hang_diag.parse(raw, 100, machine="x86_64")
    assert "kept off its CPU" in diag["verdict"], diag["verdict"]
    assert "spin??ner (tid 777, SCHED_FIFO 99, 8000.0 µs on CPU 1)" in diag["verdict"], diag["verdict"]
