"""A controller that rewrites its own shared segment while the appliance reads it (issue 26: holes 3
and 4, the segment's truncation, and a seeded random attack on every field group):
tests/fixtures/hostile_segment over the base template, uploaded, built and run through the
appliance like any project, by a student holding the lease. The attack is chosen per run through
the dashboard's setpoint (Ros2Xeno steer_left = the attack, steer_right = the seed).

Each must end the same way: the appliance stays up and answers, nothing outside the segment
reaches a file, the run ends with the ``corrupt_channel`` alarm and end reason, its record and
its log up to the violation kept (docs/developers/security.md, "The shared segment"). On main
before issue 26 the appliance copied 64 MiB past the log ring into a run file, or died.
"""

from __future__ import annotations

import os
import re
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest

from xrf_testing.grpcweb import READ_MESSAGES, read_messages
from xrf_testing.harness import Server, WsClient, wait_for
from xrf_testing.hostile import project_files
from xrf_testing.projects_support import targz, upload_and_build
from xrflab.logs.reader import open_log

REPO = Path(__file__).resolve().parents[2]
HOSTILE = REPO / "tests" / "fixtures" / "hostile_segment"
BASE = REPO / "student_projects" / "templates" / "base"

LOG_LAYOUT, MONITOR, TRUNCATE, RANDOM, LOG_HEAD, STATUS_LOCK = 1, 2, 3, 4, 5, 6


@dataclass
class Student:
    http: httpx.Client
    ws: Callable[..., WsClient]
    project: int
    build: int


@pytest.fixture(scope="module")
def mallory(server: Server) -> Iterator[Student]:
    """A student with the hostile controller uploaded and built (once for the module)."""
    http, ws = server.login("mallory", server.create_user("mallory"))
    archive = targz({**project_files(BASE), **project_files(HOSTILE)}, "hostile")
    pid, bid = upload_and_build(http, archive, "hostile.tar.gz")
    assert http.post("/api/lease/take").status_code == 200
    yield Student(http, ws, pid, bid)
    http.close()


def start_and_attack(
    server: Server, student: Student, ws: WsClient, mode: int, seed: int = 0, logged_first: bool = False
) -> dict[str, Any]:
    """Start a run of the hostile build, drive it to RUN (its logger logs there), then order the
    attack. The run's record. `logged_first`: order it only once the host's log writer has put
    records in the file (it drains the ring a quarter of its fill time apart, up to 1 s: an attack
    before the first drain leaves no record of the real layout to check)."""
    server.stop_run()
    r = student.http.post(f"/api/projects/{student.project}/builds/{student.build}/run", json={}, timeout=60)
    assert r.status_code == 201, r.text
    run = r.json()["run"]
    ws.wait_state("IDLE", timeout=30)
    for cmd, state in (("initialise", "INITIALISED"), ("start", "RUN")):
        assert ws.command(cmd)["accepted"], cmd
        ws.wait_state(state, timeout=10)
    ws.wait_type("telemetry", timeout=10)
    if logged_first:
        run_dir = server.data_dir / "runs" / str(run["id"])
        wait_for(lambda: logged_records(run_dir) > 0, 20, "the first records in the run's log file")
    ws.send({"type": "setpoint", "fields": {"steer_left": float(mode), "steer_right": float(seed)}})
    return run


def logged_records(run_dir: Path) -> int:
    """Records in the run's log files so far (a file still being written may end mid-record)."""
    n = 0
    for path in log_files(run_dir):
        try:
            n += len(open_log(path).records)
        except Exception:  # noqa: BLE001 - a header not yet complete: nothing to count yet
            continue
    return n


def output_of(server: Server, run: dict[str, Any]) -> str:
    path = server.data_dir / "runs" / str(run["id"]) / "output.txt"
    return path.read_text(errors="replace") if path.is_file() else ""


def ended_corrupt(server: Server, ws: WsClient, run: dict[str, Any], timeout: float = 30) -> dict[str, Any]:
    """The corrupt_channel alarm for `run`, then its end; the final record."""
    alarm = ws.wait_for(
        lambda m: m.get("type") == "alarm" and m.get("kind") == "corrupt_channel" and m.get("run_id") == run["id"],
        timeout,
        seen=True,
    )
    assert alarm["end_reason"] == "corrupt_channel" and "shared memory" in alarm["message"], alarm
    ws.wait_for(
        lambda m: m.get("type") == "run" and m.get("event") == "ended" and m["run"]["id"] == run["id"], 30, seen=True
    )
    row = server.http.get(f"/api/runs/{run['id']}").json()
    assert row["end_reason"] == "corrupt_channel", row
    assert "broke the rules of its shared memory" in row["message"], row
    return row


def answers(server: Server, student: Student) -> None:
    """The appliance is up and every page's API answers, for the educator and the student."""
    assert server.proc.poll() is None, "the appliance died"
    for http in (server.http, student.http):
        for path in ("/api/health", "/api/status", "/api/runs", "/api/state-machine", "/api/viz", "/api/logs/runs"):
            r = http.get(path, timeout=10)
            assert r.status_code == 200, (path, r.status_code, r.text[:300])
    with server.ws() as ws:
        ws.wait_type("state", timeout=10, seen=True)


def rss_bytes(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("no VmRSS")


def log_files(run_dir: Path) -> list[Path]:
    """The logger's files: the template logs to logs/template_<time>.bin (in xrflog format)."""
    return [p for p in (run_dir / "logs").rglob("*") if p.is_file()]


def assert_only_whole_records(server: Server, run_dir: Path, row: dict[str, Any]) -> None:
    """Every log file holds records of the loop's own layout only, numbered without a jump that
    is not counted lost, and nothing of the appliance's memory: no file the rewritten layout named,
    no byte of the educator's session."""
    assert not list(run_dir.rglob("stolen*")), sorted(p.name for p in run_dir.rglob("*"))
    files = log_files(run_dir)
    assert files, sorted(str(p.relative_to(run_dir)) for p in run_dir.rglob("*"))
    records = 0
    for path in files:
        log = open_log(path)
        seqs = [int(s) for s in log.records["seq"]]
        assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs), path
        # The loop's own records: the template's four variables, 8-byte aligned stride, and no
        # segment other than its own layout's (the rewritten one never got a header).
        assert len(log.segments) == 1 and not log.skipped, (path, log.segments, log.skipped)
        assert {v.name for v in log.variables} >= {"encoder_left", "encoder_right", "steer_left", "steer_right"}
        assert path.stat().st_size < 8 << 20, f"{path}: {path.stat().st_size} bytes: more than the ring holds"
        records += len(seqs)
    assert records == row["log_records"] > 0, (records, row)
    session = server.http.cookies.get("xrf_session")
    assert session
    for path in run_dir.rglob("*"):
        if path.is_file() and not path.is_symlink():
            assert session.encode() not in path.read_bytes(), f"{path} holds the educator's session"


def test_log_layout_and_ring_rewritten_stop_the_run_and_reach_no_file(server: Server, mallory: Student) -> None:
    """Hole 3: a new log layout naming a file, with a ring of 1024 x 64 KiB slots all ready, then
    (a second run) the ring's head 2^40 ahead. The host writer takes neither: the run ends with
    corrupt_channel, the log file ends at its last whole record of the real layout."""
    for mode in (LOG_LAYOUT, LOG_HEAD):
        with mallory.ws() as ws:
            run = start_and_attack(server, mallory, ws, mode, logged_first=True)
            wait_for(lambda: "HOSTILE log_" in output_of(server, run), 20, "the attack")  # noqa: B023
            row = ended_corrupt(server, ws, run)
        assert "log" in row["message"], row["message"]
        assert_only_whole_records(server, server.data_dir / "runs" / str(run["id"]), row)
        answers(server, mallory)


def test_monitor_ring_of_2_31_slots_of_4_gib_stops_the_run(server: Server, mallory: Student) -> None:
    """Hole 4: the monitor ring says 1 << 31 slots of 0xFFFFFFF8 bytes (the cffi module's general
    protection fault on main): the appliance survives, the run ends with corrupt_channel."""
    with mallory.ws() as ws:
        run = start_and_attack(server, mallory, ws, MONITOR)
        row = ended_corrupt(server, ws, run)
    assert "monitor" in output_of(server, run)
    assert row["log_records"] > 0, row  # its log up to the violation is kept
    answers(server, mallory)


def test_a_status_block_kept_locked_while_the_loop_runs_stops_the_run(server: Server, mallory: Student) -> None:
    """The status seqlock inverted (seq odd between the loop's writes): a read never holds the
    appliance (the last good status meanwhile), and once the block has stayed locked for
    LOCKED_LIMIT_S the run ends with corrupt_channel (channels/status.py). Before, each read spun
    20 ms on the event loop and the appliance swallowed the error: the run went on unjudged."""
    with mallory.ws() as ws:
        run = start_and_attack(server, mallory, ws, STATUS_LOCK)
        wait_for(lambda: "HOSTILE status_lock" in output_of(server, run), 20, "the attack")
        row = ended_corrupt(server, ws, run)
    assert "status block stays locked" in row["message"], row["message"]
    answers(server, mallory)


def test_truncating_the_segment_is_refused(server: Server, mallory: Student) -> None:
    """The segment is a memfd the appliance sealed at its size: ftruncate on every descriptor the
    controller can reach fails (on main /dev/shm/xrf was the loop's own file: the appliance's next
    read of it was a SIGBUS), and the run goes on."""
    with mallory.ws() as ws:
        run = start_and_attack(server, mallory, ws, TRUNCATE)
        text = wait_for(lambda: "HOSTILE truncate: done" in (t := output_of(server, run)) and t, 20, "the attempts")
        tried = re.findall(r"^HOSTILE truncate (\S+): (SUCCEEDED|blocked) ?(.*)$", text, re.M)
        assert tried and all(result == "blocked" for _, result, _ in tried), text
        # The loop's own descriptor of it: refused by the seal, not for want of a descriptor.
        assert ("XRF_SHM_FD", "blocked", "(Operation not permitted)") in tried, text
        ws.messages.clear()
        ws.wait_type("telemetry", timeout=10)  # the loop and the appliance's reader go on
        answers(server, mallory)
        assert mallory.http.post("/api/runs/current/stop", timeout=30).status_code == 200
    row = server.http.get(f"/api/runs/{run['id']}").json()
    assert row["end_reason"] == "stopped", row
    answers(server, mallory)


@dataclass
class Load:
    """What reads a run while it is attacked: the rerun live stream, the 3D view, the run pages."""

    errors: list[str]
    rerun_messages: int = 0
    polls: int = 0


def _read_live_stream(student: Student, run_id: int, load: Load, stop: threading.Event) -> None:
    try:
        wait_for(lambda: student.http.get("/api/logs/rerun").json()["live_run"] == run_id, 20, "the live proxy")
        while not stop.is_set():
            got = read_messages(student.http, READ_MESSAGES, timeout=5, quiet=3, until=lambda _: stop.is_set())
            load.rerun_messages += len(got.messages)
    except Exception as exc:  # reported by the test
        load.errors.append(f"live stream: {exc!r}")


def _poll_pages(student: Student, run_id: int, load: Load, stop: threading.Event) -> None:
    paths = ("/api/viz/state", "/api/viz", "/api/status", f"/api/runs/{run_id}", "/api/logs/rerun")
    while not stop.is_set():
        for path in paths:
            try:
                r = student.http.get(path, timeout=10)
                if r.status_code != 200:
                    load.errors.append(f"{path}: {r.status_code} {r.text[:200]}")
            except httpx.HTTPError as exc:
                load.errors.append(f"{path}: {exc!r}")
        load.polls += 1
        time.sleep(0.1)


@pytest.mark.parametrize("seed", [26, 2026])
def test_random_fields_at_random_times_while_everything_reads(server: Server, mallory: Student, seed: int) -> None:
    """The end-to-end hostile segment: seeded random values in random fields of every group at
    random times, while the appliance reads, logs, streams to a dashboard WebSocket, the rerun
    live stream and the 3D view: the appliance stays up, its memory flat, every route answers,
    and the run ends with the corrupt_channel alarm."""
    pid = server.proc.pid
    stop = threading.Event()
    load = Load([])
    with mallory.ws() as ws:
        run = start_and_attack(server, mallory, ws, 0)  # to RUN first: no attack ordered yet
        readers = [
            threading.Thread(target=_read_live_stream, args=(mallory, run["id"], load, stop), daemon=True),
            threading.Thread(target=_poll_pages, args=(mallory, run["id"], load, stop), daemon=True),
        ]
        for t in readers:
            t.start()
        time.sleep(2.0)  # the point: the readers hammer a while before the memory baseline
        rss_before = rss_bytes(pid)
        ws.send({"type": "setpoint", "fields": {"steer_left": float(RANDOM), "steer_right": float(seed)}})
        try:
            row = ended_corrupt(server, ws, run, timeout=40)
        finally:
            stop.set()
            for t in readers:
                t.join(15)
        dashboard = [m for m in ws.messages if m.get("type") in ("telemetry", "monitor", "state")]
    rss_after = rss_bytes(pid)
    assert "HOSTILE random: seed" in output_of(server, run)
    assert not load.errors, load.errors[:10]
    assert load.polls > 5 and dashboard, (load, len(dashboard))
    assert rss_after - rss_before < 64 << 20, f"the appliance grew by {(rss_after - rss_before) >> 20} MiB"
    assert row["status"] in ("ended", "crashed"), row
    answers(server, mallory)
    # Nothing the attack named became a file outside the run's own names, none holds a session.
    run_dir = server.data_dir / "runs" / str(run["id"])
    session = server.http.cookies.get("xrf_session") or ""
    for path in run_dir.rglob("*"):
        if path.is_file() and not path.is_symlink():
            assert session.encode() not in path.read_bytes(), path
    assert os.path.isdir(run_dir)
