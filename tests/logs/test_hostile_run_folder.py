"""Issue 26, guest-writable folders: a student's controller turns its own run folder against the
appliance while it runs (tests/fixtures/hostile_run_folder: the base template plus a thread that
plants links, FIFOs, odd names and a file it keeps truncating), uploaded, built and run through
a real appliance like any project. Whatever it plants:

- nothing outside the run folder is read (timing.jsonl -> a root-only file, a log name -> a
  secret of the data folder, a folder link), listed or served;
- nothing outside is written (viz/meta.json -> a file, viz -> a folder): the targets unchanged;
- a FIFO blocks nothing (the routes answer, the run stops, the appliance stays up);
- a file truncated under the reader does not kill the appliance (SIGBUS);
- names that are not UTF-8 are listed and downloadable, escaped;
- hard links to files elsewhere are not served (planted by the test: ``fs.protected_hardlinks``
  stops the guest itself from linking a file it cannot read);
- clean-up of the run's /dev/shm folder removes the links, not what they point to.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from xrf_testing.harness import Server, shared_builds_root, start_server, stop_server, wait_for
from xrf_testing.hostile import project_files
from xrf_testing.projects_support import build_and_wait, reachable_tmp, targz
from xrf_testing.writers import xrflog_segment
from xrflab.channels.segment import SEGMENT_LINK_SUFFIX

REPO = Path(__file__).resolve().parents[2]
HOSTILE = REPO / "tests" / "fixtures" / "hostile_run_folder"
BASE = REPO / "student_projects" / "templates" / "base"
ROOT_SECRET = b"ROOT-ONLY-SECRET shadow-like line\n"
DATA_SECRET = b'{"enrolment-like": "bench key that signs room tokens"}\n'
PRECIOUS = b"PRECIOUS: written by nobody but the test\n"
XRF2_LOG = b"x,y\n5,5\n" + b"\0" * 16 * 4


@pytest.fixture(scope="module")
def data_dir() -> Iterator[Path]:
    d = reachable_tmp("hostile-folder")
    yield d
    shutil.rmtree(d, ignore_errors=True)


@pytest.fixture(scope="module")
def outside() -> Iterator[Path]:
    """Files outside the data folder: a root-only secret (the appliance's own when not root), a
    file and a folder nobody may write, a folder holding a log."""
    d = reachable_tmp("hostile-outside")
    os.chmod(d, 0o700)
    (d / "secret").write_bytes(ROOT_SECRET)
    (d / "target").write_bytes(PRECIOUS)
    (d / "dir").mkdir()
    (d / "logs").mkdir()
    (d / "logs" / "leak.bin").write_bytes(XRF2_LOG)
    for p in (d / "secret", d / "target"):
        os.chmod(p, 0o600)
    yield d
    shutil.rmtree(d, ignore_errors=True)


@pytest.fixture(scope="module")
def server(data_dir: Path) -> Iterator[Server]:
    s = start_server(data_dir, shared_builds_root())
    yield s
    stop_server(s)


class Student:
    """mallory, holding the lease, with the hostile controller built."""

    def __init__(self, server: Server, http: httpx.Client, pid: int, bid: int) -> None:
        self.server, self.http, self.pid, self.bid = server, http, pid, bid

    def run(self, scenario: str) -> tuple[int, Path]:
        """A run of the controller doing `scenario`; returns (run id, run folder) once it is done."""
        self.http.post("/api/runs/current/stop", timeout=30)
        r = self.http.post(f"/api/projects/{self.pid}/builds/{self.bid}/run", json={}, timeout=60)
        assert r.status_code == 201, r.text
        run_id = r.json()["run"]["id"]
        folder = self.server.data_dir / "runs" / str(run_id)
        (folder / "hostile-scenario").write_text(scenario + "\n")
        output = folder / "output.txt"
        text = wait_for(
            lambda: f"HOSTILE {scenario} " in output.read_text(errors="replace") and output.read_text(errors="replace"),
            60,
            f"the controller's '{scenario}' plants",
        )
        assert f"HOSTILE {scenario} ready" in text, text[-2000:]
        return run_id, folder

    def stop(self) -> None:
        r = self.http.post("/api/runs/current/stop", timeout=30)
        assert r.status_code == 200, r.text


@pytest.fixture(scope="module")
def student(server: Server, outside: Path) -> Iterator[Student]:
    server.stop_run()
    http, _ = server.login("mallory", server.create_user("mallory"))
    secret = server.data_dir / "bench-secret.json"  # a secret of the data folder (as room/enrolment.json)
    secret.write_bytes(DATA_SECRET)
    os.chmod(secret, 0o600)
    targets = (
        f'#define HOSTILE_SECRET "{outside / "secret"}"\n'
        f'#define HOSTILE_DATA_SECRET "{secret}"\n'
        f'#define HOSTILE_WRITE_TARGET "{outside / "target"}"\n'
        f'#define HOSTILE_WRITE_DIR "{outside / "dir"}"\n'
        f'#define HOSTILE_OUTSIDE_LOGS "{outside / "logs"}"\n'
    ).encode()
    files = {**project_files(BASE), **project_files(HOSTILE), "src/targets.h": targets}
    r = http.post("/api/projects", files={"file": ("hostile.tar.gz", targz(files, "hostile"), "application/gzip")})
    assert r.status_code == 201, r.text
    pid = r.json()["project"]["id"]
    b = build_and_wait(http, pid)
    assert b["status"] == "ok", http.get(f"/api/projects/{pid}/builds/{b['id']}/log").text[-3000:]
    assert http.post("/api/lease/take").status_code == 200
    yield Student(server, http, pid, b["id"])
    http.post("/api/runs/current/stop", timeout=30)
    http.close()


def _untouched(outside: Path) -> None:
    assert (outside / "target").read_bytes() == PRECIOUS, "the appliance wrote through a planted link"
    assert list((outside / "dir").iterdir()) == [], "the appliance wrote into a folder outside"
    assert (outside / "secret").read_bytes() == ROOT_SECRET
    assert sorted(p.name for p in outside.iterdir()) == ["dir", "logs", "secret", "target"]


def _names(listing: dict[str, Any]) -> set[str]:
    return {f["name"] for f in listing["files"]}


def _alive(server: Server) -> None:
    assert server.proc.poll() is None, f"the appliance died (exit {server.proc.returncode})"
    assert server.http.get("/api/health", timeout=10).status_code == 200


def test_planted_links_are_neither_read_nor_written(student: Student, outside: Path) -> None:
    run_id, folder = student.run("links")
    assert (folder / "timing.jsonl").is_symlink()
    for http in (student.http, student.server.http):  # the run's owner, and an educator
        r = http.get(f"/api/logs/runs/{run_id}/timing")
        assert r.status_code == 404, r.status_code
        assert b"ROOT-ONLY" not in r.content
        listing = http.get(f"/api/logs/runs/{run_id}")
        assert listing.status_code == 200, listing.text
        assert listing.json()["timing"] is False
        names = _names(listing.json())
        assert not {n for n in names if n.startswith(("stolen", "outside", "viz"))}, names
        for name in ("stolen.bin", "stolen.txt", "outside/leak.bin", "timing.jsonl"):
            for fmt in ("raw", "csv", "parquet"):
                r = http.get(f"/api/logs/runs/{run_id}/files/{name}", params={"fmt": fmt})
                assert r.status_code == 404, (name, fmt, r.status_code)
                assert b"enrolment-like" not in r.content and b"ROOT-ONLY" not in r.content
    student.stop()  # the 3D recorder closes its recording now: meta.json -> the target
    _untouched(outside)
    r = student.http.get(f"/api/logs/runs/{run_id}/timing")
    assert r.status_code == 404 and b"ROOT-ONLY" not in r.content
    _alive(student.server)


def test_a_viz_folder_swapped_for_a_link_is_not_written_through(student: Student, outside: Path) -> None:
    run_id, folder = student.run("vizdir")
    assert (folder / "viz").is_symlink()
    student.stop()
    _untouched(outside)
    # Replays refuse it as a recording (the run's own one was renamed away by the controller).
    r = student.server.http.get("/api/viz/recordings")
    assert r.status_code == 200 and run_id not in [x["run_id"] for x in r.json()]
    _alive(student.server)


def test_names_that_are_not_utf8_are_listed_and_downloadable(student: Student) -> None:
    run_id, folder = student.run("names")
    r = student.http.get(f"/api/logs/runs/{run_id}")
    assert r.status_code == 200, r.text
    files = {f["name"]: f for f in r.json()["files"]}
    assert "bad\\xff.bin" in files and "back\\\\slash.bin" in files, sorted(files)
    assert files["bad\\xff.bin"]["kind"] == "xrf2" and files["bad\\xff.bin"]["records"] == 1000
    on_disk = (folder / os.fsdecode(b"bad\xff.bin")).read_bytes()
    for name, want in (("bad\\xff.bin", on_disk), ("back\\\\slash.bin", (folder / "back\\slash.bin").read_bytes())):
        quoted = name.replace("\\", "%5C")  # what the Runs page sends (encodeURIComponent)
        raw = student.http.get(f"/api/logs/runs/{run_id}/files/{quoted}")
        assert raw.status_code == 200, raw.text
        assert raw.content == want
        assert "filename=" in raw.headers["content-disposition"]
    csv = student.http.get(f"/api/logs/runs/{run_id}/files/bad%5Cxff.bin", params={"fmt": "csv"})
    assert csv.status_code == 200 and csv.text.count("\n") == 1001
    student.stop()
    # A log the loop wrote itself may also name a variable with a lone surrogate (JSON \udcff):
    # planted here as the loop could have.
    (folder / "odd.xrf").write_bytes(xrflog_segment([("ok", 5), ("bad\udcff", 5)], [(1.0, 2.0), (3.0, 4.0)]))
    r = student.http.get(f"/api/logs/runs/{run_id}")
    assert r.status_code == 200, r.text
    (odd,) = [f for f in r.json()["files"] if f["name"] == "odd.xrf"]
    assert [v["name"] for v in odd["variables"]] == ["ok", "bad\\udcff"]
    for fmt in ("csv", "parquet", "rrd"):
        assert student.http.get(f"/api/logs/runs/{run_id}/files/odd.xrf", params={"fmt": fmt}).status_code == 200
    assert student.http.get(f"/api/logs/runs/{run_id}").status_code == 200
    assert student.http.get("/api/logs/runs").status_code == 200


def test_hard_links_to_files_elsewhere_are_not_served(student: Student, server: Server, outside: Path) -> None:
    run_id, folder = student.run("names")
    student.stop()
    # What a guest could plant on a system without fs.protected_hardlinks (or for a file it may
    # read): hard links to a secret of the data folder, one where timing.jsonl was.
    secret = server.data_dir / "bench-secret.json"
    log_secret = server.data_dir / "secret-log.bin"
    log_secret.write_bytes(XRF2_LOG)
    os.chmod(log_secret, 0o600)
    (folder / "timing.jsonl").unlink(missing_ok=True)
    os.link(secret, folder / "timing.jsonl")
    os.link(log_secret, folder / "hard.bin")
    try:
        r = student.http.get(f"/api/logs/runs/{run_id}/timing")
        assert r.status_code == 404 and b"enrolment-like" not in r.content
        assert "hard.bin" not in _names(student.http.get(f"/api/logs/runs/{run_id}").json())
        assert student.http.get(f"/api/logs/runs/{run_id}/files/hard.bin").status_code == 404
    finally:
        (folder / "hard.bin").unlink()
        (folder / "timing.jsonl").unlink()
        log_secret.unlink()


def test_a_file_truncated_under_the_reader_does_not_kill_the_appliance(student: Student) -> None:
    run_id, _ = student.run("truncate")
    deadline = time.monotonic() + 8
    answers = []
    while time.monotonic() < deadline:
        for fmt in ("csv", "parquet", "raw"):
            try:
                r = student.http.get(f"/api/logs/runs/{run_id}/files/big.bin", params={"fmt": fmt}, timeout=30)
                answers.append(r.status_code)
            except httpx.HTTPError as exc:  # a stream cut short is fine; a dead appliance is not
                answers.append(type(exc).__name__)
            assert student.server.proc.poll() is None, f"the appliance died (exit {student.server.proc.returncode})"
        assert student.http.get(f"/api/logs/runs/{run_id}").status_code == 200
    assert 200 in answers, answers
    student.stop()
    _alive(student.server)


def test_shm_clean_up_removes_the_links_not_their_targets(student: Student, server: Server, outside: Path) -> None:
    run_id, folder = student.run("shm")
    shm = server.http.get(f"/api/runs/{run_id}").json()["shm"]
    # The run's shm name is the appliance's link to its sealed segment, named after the loop's
    # /dev/shm folder (server/launch.segment_link), or <folder>/<name> where no link is made.
    shm_dir = Path("/dev/shm") / shm.split("/")[0].removesuffix(SEGMENT_LINK_SUFFIX)
    assert (shm_dir / "outside").is_symlink()
    (outside / "dir" / "keep").write_text("mine")
    try:
        student.stop()
        wait_for(lambda: not shm_dir.exists(), 10, "the run's /dev/shm folder to go")
        assert (outside / "dir" / "keep").read_text() == "mine"
        assert (outside / "target").read_bytes() == PRECIOUS
        assert (folder / "links" / "outside").is_symlink()  # the run folder is the run's record: kept
    finally:
        (outside / "dir" / "keep").unlink()
    _untouched(outside)


def test_fifos_block_nothing(student: Student, server: Server, outside: Path) -> None:
    """Last: on an appliance that opens a FIFO for writing, the stop hangs it for good."""
    run_id, folder = student.run("fifos")
    t0 = time.monotonic()
    for path in ("timing", ""):
        r = student.http.get(f"/api/logs/runs/{run_id}/{path}".rstrip("/"), timeout=10)
        assert r.status_code in (200, 404)
    names = _names(student.http.get(f"/api/logs/runs/{run_id}", timeout=10).json())
    assert not {"fifo.bin", "fifo.xrf", "timing.jsonl"} & names
    for name in ("fifo.bin", "fifo.xrf"):
        assert student.http.get(f"/api/logs/runs/{run_id}/files/{name}", timeout=10).status_code == 404
    r = student.http.post("/api/runs/current/stop", timeout=20)
    assert r.status_code == 200, r.text
    assert time.monotonic() - t0 < 30
    _alive(server)
    assert server.http.get("/api/viz/recordings", timeout=10).status_code == 200
    assert student.http.get(f"/api/logs/runs/{run_id}", timeout=10).status_code == 200
    _untouched(outside)
