"""Issue 14 item 2: wherever a controller says its log goes, it lands in the run folder.

- The runtime's XenoFileHandler maps XRF2 names (``/home/<name>/logs/log``, ``../x``) into the run
  folder and prints where (at set-up).
- The appliance's host writer treats the name the loop publishes as untrusted: a name outside the
  run folder is mapped into it, ``..`` is refused, and nothing below the run folder is followed
  (symlinked folders or files, FIFOs, hard links): an evil loop cannot make the appliance write
  anywhere else. Played here by a real loop whose published name the test overwrites.
- Through the appliance: an XRF2 project (the fixture, built by CMake) whose logger writes to
  ``/home/student/logs/log`` finds its log in the run's downloads, and it decodes; the console
  says where it went; nothing is written at /home/student.
- The run's downloads list nested files but never a symlink (to another run's log, say).
"""

from __future__ import annotations

import io
import os
import shutil
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from xrf_testing.harness import stop_server
from xrf_testing.logs_support import REPO, shared_builds_root, start_server, wait_for
from xrf_testing.loops import LoopProcess
from xrflab.logs import open_log
from xrflab.logs.host_writer import HostLogWriter
from xrflab.logs.logformat import MAGIC
from xrflab.runfolder import RunPathError, confine, open_in

XRF2_NAME = "xrf2-home-log"
STUDENT_LOG = "/home/student/logs/log"  # what the student's XenoFileHandler names
STUDENT_FILE = "home/student/logs/log.bin"  # where it must land, relative to the run


# ---- the name rule and the safe open, on a real file system -----------------------------------


def test_confine_maps_absolute_names_and_refuses_dot_dot(tmp_path: Path) -> None:
    run = tmp_path / "runs" / "12"
    assert confine(run, "/home/x/logs/log.xrf") == "home/x/logs/log.xrf"
    assert confine(run, "/temp//a/./b.bin") == "temp/a/b.bin"
    assert confine(run, f"{run}/home/x/log.xrf") == "home/x/log.xrf"  # the runtime's mapped name
    assert confine(run, "logs/probe.xrf") == "logs/probe.xrf"
    for bad in ("../x.xrf", "/home/../../etc/passwd", "a/../../b", "", "/", "a\0b"):
        with pytest.raises(RunPathError):
            confine(run, bad)


def test_open_in_follows_no_symlink_and_takes_plain_files_only(tmp_path: Path) -> None:
    run, outside = tmp_path / "run", tmp_path / "outside"
    run.mkdir()
    outside.mkdir()
    secret = outside / "secret"
    secret.write_text("not yours")
    flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND
    (run / "dirlink").symlink_to(outside)
    (run / "filelink.xrf").symlink_to(secret)
    os.mkfifo(run / "fifo.xrf")
    os.link(secret, run / "hardlink.xrf")
    for rel in ("dirlink/x.xrf", "filelink.xrf", "fifo.xrf", "hardlink.xrf"):
        t0 = time.monotonic()
        with pytest.raises(OSError):
            os.close(open_in(run, rel, flags, create_dirs=True))
        assert time.monotonic() - t0 < 1.0, f"{rel}: open blocked"
    assert sorted(p.name for p in outside.iterdir()) == ["secret"] and secret.read_text() == "not yours"
    fd = open_in(run, "a/b/c.xrf", flags, 0o666, create_dirs=True)
    os.close(fd)
    assert (run / "a/b/c.xrf").is_file()
    assert (run / "a/b/c.xrf").stat().st_mode & 0o007 == 0, "a log is never world-readable"


# ---- the host writer against a real loop whose published name is hostile ----------------------


@pytest.fixture
def published_loop(probe: Path, shm_name: str, tmp_path: Path) -> Iterator[LoopProcess]:
    """The probe in INITIALISED with its log published (host writer mode), logging every cycle."""
    lp = LoopProcess(
        probe,
        shm_name,
        tmp_path,
        capture=False,
        XRF_LOG_WRITER="host",
        XRF_TRANSPORT="sim",
        XRF_LOG_DIR=str(tmp_path / "loopdir"),
    )
    lp.command("initialise", "INITIALISED")
    yield lp
    if lp.proc.poll() is None:
        lp.proc.kill()
        lp.proc.wait(5)


def _publish(lp: LoopProcess, path: str) -> None:
    """Overwrite the log's name in the shared memory, as a loop could publish anything there."""
    from xrflab import channels as chmod

    m = lp.ch.shm.log_meta
    raw = path.encode() + b"\0"
    chmod.ffi.memmove(m.path, raw, len(raw))


def _write_once(lp: LoopProcess, run: Path) -> tuple[HostLogWriter, list[str], list[str]]:
    alarms: list[str] = []
    notes: list[str] = []
    w = HostLogWriter(lp.ch, {"run": "12"}, run, on_alarm=alarms.append, on_note=notes.append, timing=False)
    lp.wait_cycles(50)
    w.drain()
    w.finish()
    return w, alarms, notes


def test_host_writer_maps_an_outside_name_into_the_run(published_loop: LoopProcess, tmp_path: Path) -> None:
    run = tmp_path / "runs" / "12"
    run.mkdir(parents=True)
    outside = tmp_path / "home-outside"
    _publish(published_loop, f"{outside}/logs/log.xrf")
    w, alarms, notes = _write_once(published_loop, run)
    assert alarms == [] and w.stats.failed == ""
    inside = run / str(outside).lstrip("/") / "logs/log.xrf"
    assert w.stats.files == [str(inside)]
    assert not outside.exists(), "the writer wrote where the loop said, outside the run"
    log = open_log(inside)
    assert len(log) == w.stats.records > 0
    assert notes == [f"log {outside}/logs/log.xrf -> runs/12/{str(outside).lstrip('/')}/logs/log.xrf"]


@pytest.mark.parametrize("case", ["dot-dot", "symlinked-folder", "symlinked-file", "fifo"])
def test_host_writer_never_writes_outside_the_run(published_loop: LoopProcess, tmp_path: Path, case: str) -> None:
    run = tmp_path / "runs" / "12"
    run.mkdir(parents=True)
    outside = tmp_path / "precious"
    outside.mkdir()
    (outside / "accounts.sqlite3").write_bytes(b"SQLite format 3\0")
    if case == "dot-dot":
        _publish(published_loop, "../precious/accounts.sqlite3")
    elif case == "symlinked-folder":  # the loop made <run>/home a link to a folder of the appliance
        (run / "home").symlink_to(outside)
        _publish(published_loop, "/home/accounts.sqlite3")
    elif case == "symlinked-file":
        (run / "log.xrf").symlink_to(outside / "accounts.sqlite3")
        _publish(published_loop, "/log.xrf")
    else:
        os.mkfifo(run / "log.xrf")
        _publish(published_loop, "log.xrf")
    t0 = time.monotonic()
    w, alarms, _ = _write_once(published_loop, run)
    assert time.monotonic() - t0 < 5.0
    assert w.stats.failed and alarms == [w.stats.failed], "a refusal is said, not silent"
    assert w.stats.records == 0 and w.stats.unwritten > 0
    assert sorted(p.name for p in outside.iterdir()) == ["accounts.sqlite3"]
    assert (outside / "accounts.sqlite3").read_bytes() == b"SQLite format 3\0"
    expect = {
        "dot-dot": "leaves the run folder",
        "symlinked-folder": "cannot write the log file",
        "symlinked-file": "cannot write the log file",
        "fifo": "cannot write the log file",
    }[case]
    assert expect in w.stats.failed, w.stats.failed


def test_runtime_maps_xrf2_names_and_says_so(probe: Path, shm_name: str, tmp_path: Path) -> None:
    """The runtime's own mapping (XRF_LOG_DIR set): the probe's relative name stays, and the
    set-up line says where the file goes; the in-band writer writes it there."""
    run = tmp_path / "run"
    lp = LoopProcess(
        probe, shm_name, tmp_path, capture=True, XRF_LOG_DIR=str(run), XRF_TRANSPORT="sim", XRF_MAX_CYCLES="300"
    )
    lp.command("initialise", "INITIALISED")
    rc, out = lp.finish()
    assert rc == 0, out
    assert "xrf: log logs/probe_" in out and " in the run folder" in out, out
    assert [p.parent.name for p in run.rglob("probe_*.xrf")] == ["logs"]


# ---- through the appliance: an XRF2 project writing to /home/student/logs/log ----------------


def _xrf2_project() -> Path:
    """tests/fixtures/xrf2_project with a 20-sim controller (the template's, renamed as
    tests/projects does) and its XenoFileHandler naming /home/student/logs/log. Kept at a stable
    path (the shared build folder's CMake cache remembers it); files rewritten only when changed."""
    root = REPO / ".cache" / "log-paths-projects"
    staging = root / "staging"
    shutil.rmtree(staging, ignore_errors=True)
    shutil.copytree(REPO / "tests/fixtures/xrf2_project", staging)
    shutil.copytree(REPO / "student_projects/templates/20sim/controller", staging / "controller")
    for path in sorted((staging / "controller").rglob("*")):
        if path.is_file():
            path.write_text(path.read_text().replace("LoopController", "PanTiltController"))
            if "LoopController" in path.name:
                path.rename(path.with_name(path.name.replace("LoopController", "PanTiltController")))
    loop_cpp = staging / "src/ControlLoop.cpp"
    text = loop_cpp.read_text()
    assert '"./xrf2_logging/pantilt"' in text
    loop_cpp.write_text(text.replace('"./xrf2_logging/pantilt"', f'"{STUDENT_LOG}"'))
    project = root / "examples" / XRF2_NAME
    for src in sorted(staging.rglob("*")):
        dst = project / src.relative_to(staging)
        if src.is_dir():
            dst.mkdir(parents=True, exist_ok=True)
        elif not dst.is_file() or dst.read_bytes() != src.read_bytes():
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dst)
    shutil.rmtree(staging)
    return root


@pytest.fixture(scope="module")
def xrf2_server(tmp_path_factory: pytest.TempPathFactory):
    s = start_server(tmp_path_factory.mktemp("data"), shared_builds_root(), projects_dir=str(_xrf2_project()))
    yield s
    stop_server(s)


def test_xrf2_log_in_home_lands_in_the_runs_downloads(xrf2_server) -> None:
    server = xrf2_server
    home = Path("/home/student")
    existed = home.exists()
    before = set(home.rglob("*")) if existed else set()
    server.stop_run()
    with server.ws() as ws:
        r = server.http.post("/api/runs", json={"build": XRF2_NAME}, timeout=600)
        assert r.status_code == 201, r.text
        run_id = r.json()["id"]
        ws.wait_state("IDLE", timeout=30)
        for cmd, state in (("initialise", "INITIALISED"), ("start", "RUN")):
            assert ws.command(cmd)["accepted"], cmd
            ws.wait_state(state, timeout=10)
        # The console: the runtime's set-up line (stdout) and the appliance's (where it wrote).
        ws.wait_for(
            lambda m: (
                m.get("type") == "monitor"
                and any(
                    f"xrf: log {STUDENT_LOG}.bin -> {STUDENT_FILE} in the run folder" in ln["text"] for ln in m["lines"]
                )
            ),
            timeout=10,
            seen=True,
        )
        note = ws.wait_for(
            lambda m: m.get("type") == "monitor" and m.get("source") == "appliance", timeout=10, seen=True
        )
        assert note["lines"][0]["text"] == f"log {STUDENT_FILE} -> runs/{run_id}/{STUDENT_FILE}", note
        time.sleep(0.5)  # ~250 records at 500 Hz
        assert ws.command("stop")["accepted"]
        ws.wait_state("STOPPED", timeout=10)
    server.stop_run()

    detail = wait_for(
        lambda: (d := server.http.get(f"/api/logs/runs/{run_id}").json())["run"]["status"] != "running" and d,
        timeout=20,
        what="the run's end",
    )
    names = [f["name"] for f in detail["files"]]
    assert names == [STUDENT_FILE], detail["files"]
    info = detail["files"][0]
    assert info["kind"] == "xrflog" and info["records"] > 100 and info["lost"] == 0
    assert [v["name"] for v in info["variables"]] == [
        "set_pan",
        "pan",
        "set_tilt",
        "tilt",
        "encoder_pan",
        "encoder_tilt",
        "enabled",
    ]
    assert detail["run"]["log_records"] == info["records"]

    raw = server.http.get(f"/api/logs/runs/{run_id}/files/{STUDENT_FILE}", params={"fmt": "raw"})
    assert raw.status_code == 200 and raw.content[:8] == MAGIC
    csv = server.http.get(f"/api/logs/runs/{run_id}/files/{STUDENT_FILE}", params={"fmt": "csv"})
    assert csv.status_code == 200
    table = np.genfromtxt(io.StringIO(csv.text), delimiter=",", names=True)
    assert len(table) == info["records"] and np.all(np.diff(table["cycle"]) > 0)
    mat = server.http.get(f"/api/logs/runs/{run_id}/files/{STUDENT_FILE}", params={"fmt": "mat"})
    assert mat.status_code == 200 and mat.content[:6] == b"MATLAB"
    after = set(home.rglob("*")) if home.exists() else set()
    assert home.exists() == existed and after == before, "the log was written at /home/student"


def test_downloads_list_no_symlink(xrf2_server) -> None:
    """A link planted in a run folder (to another run's log) is neither listed nor served."""
    server = xrf2_server
    runs = server.http.get("/api/logs/runs").json()
    assert runs, "needs the run of the test above"
    victim = max(r["id"] for r in runs)
    server.stop_run()
    r = server.http.post("/api/runs", json={"build": XRF2_NAME, "max_cycles": 10}, timeout=120)
    assert r.status_code == 201, r.text
    thief = r.json()["id"]
    wait_for(
        lambda: server.http.get(f"/api/logs/runs/{thief}").json()["run"]["status"] != "running",
        timeout=60,  # a start in the run sandbox takes seconds on a loaded 2-core CI host
        what="the short run's end",
    )
    run_dir = server.data_dir / "runs"
    (run_dir / str(thief) / "stolen.xrf").symlink_to(run_dir / str(victim) / STUDENT_FILE)
    (run_dir / str(thief) / "stolen-dir").symlink_to(run_dir / str(victim))
    files = server.http.get(f"/api/logs/runs/{thief}").json()["files"]
    assert not [f for f in files if f["name"].startswith("stolen")], files
    for name in ("stolen.xrf", f"stolen-dir/{STUDENT_FILE}"):
        assert server.http.get(f"/api/logs/runs/{thief}/files/{name}").status_code == 404
