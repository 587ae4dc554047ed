"""The grading routes on a real appliance: an educator stores an assignment's scenario (a typo is
refused with its line), a student checks their copy of the assignment (graded in the run
sandbox, rate-limited, never another student's), the educator's table and CSV (issue 32)."""

from __future__ import annotations

import hashlib
import shutil
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from xrf_testing.harness import UNCONFINED_UNLESS_ROOT, Server, shared_builds_root, start_server, stop_server
from xrf_testing.projects_support import build_and_wait, reachable_tmp, targz
from xrflab.projects.assignments import Assignments

pytestmark = pytest.mark.live

REPO = Path(__file__).resolve().parents[2]
JIWY = REPO / "student_projects" / "examples" / "jiwy"
SCENARIO = (REPO / "student_projects" / "scenarios" / "jiwy.toml").read_text()


def _install_assignment(data_dir: Path) -> None:
    files = {
        str(p.relative_to(JIWY)): p.read_bytes() for p in JIWY.rglob("*") if p.is_file() and "build" not in p.parts
    }
    archive = data_dir / "jiwy.tar.gz"
    archive.write_bytes(targz(files, "jiwy"))
    digest = hashlib.sha256(archive.read_bytes()).hexdigest()
    Assignments(data_dir / "assignments").install({"id": "lab1", "name": "Lab 1", "sha256": digest}, archive)
    archive.unlink()


@pytest.fixture
def server() -> Iterator[Server]:
    data = reachable_tmp("grading")  # the build user must reach the projects
    try:
        _install_assignment(data)
        srv = start_server(data, shared_builds_root(), allow_unconfined=UNCONFINED_UNLESS_ROOT)
        try:
            yield srv
        finally:
            stop_server(srv)
    finally:
        shutil.rmtree(data, ignore_errors=True)


def test_a_student_checks_their_assignment_and_the_educator_sees_the_table(server: Server) -> None:
    typo = SCENARIO.replace('signal = "pan"\nat = 0.2', 'signal = "pann"\nat = 0.2', 1)
    r = server.http.put("/api/assignments/lab1/scenario", content=typo.encode())
    line = typo.splitlines().index('signal = "pann"') + 1
    assert r.status_code == 422 and r.json()["detail"]["line"] == line, r.text
    assert "unknown signal 'pann'" in r.json()["detail"]["error"]
    r = server.http.put("/api/assignments/lab1/scenario", content=SCENARIO.encode())
    assert r.status_code == 200, r.text
    assert [c["id"] for c in r.json()["checks"]] == ["runs", "pan_overshoot", "pan_settles", "tilt_sse", "pwm_pan"]

    alice, _ = server.login("alice", server.create_user("alice"))
    bob, _ = server.login("bob", server.create_user("bob"))
    mine = [p for p in alice.get("/api/projects").json() if p["origin"] == "assignment:lab1"]
    assert len(mine) == 1
    pid = mine[0]["id"]
    b = build_and_wait(alice, pid)
    assert b["status"] == "ok", (b["result"], alice.get(f"/api/projects/{pid}/builds/{b['id']}/log").text[-2000:])
    assert alice.get("/api/assignments/lab1/scenario").json()["robot"] == "jiwy"

    r = alice.post(f"/api/projects/{pid}/grade")
    assert r.status_code == 202, r.text
    again = alice.post(f"/api/projects/{pid}/grade")
    assert again.status_code == 429 and int(again.headers["Retry-After"]) > 0
    assert bob.get(f"/api/projects/{pid}/grade").status_code == 404  # not bob's to see
    assert bob.post(f"/api/projects/{pid}/grade").status_code == 404
    deadline = time.monotonic() + 60
    while True:
        got = alice.get(f"/api/projects/{pid}/grade").json()
        if got["result"] is not None:
            break
        assert time.monotonic() < deadline, got
        time.sleep(0.2)  # polling the job, as the page does
    result = got["result"]
    assert result["status"] == "completed", (result["reason"], result["output_tail"])
    assert result["earned"] == result["points"] == 8
    assert result["virtual_time"] is True  # in the sandbox too: the loop got XRF_VIRTUAL_TIME
    assert result["run"] is not None and any(c["plot"] for c in result["checks"])
    assert alice.get(f"/api/logs/runs/{result['run']}").status_code == 200  # its log, where every run's is

    table = server.http.get("/api/assignments/lab1/grades").json()
    assert [r["owner"] for r in table["rows"]] == ["alice"] or "alice" in [r["owner"] for r in table["rows"]]
    row = next(r for r in table["rows"] if r["owner"] == "alice")
    assert row["status"] == "completed" and row["checks"]["pan_overshoot"]["passed"]
    assert alice.get("/api/assignments/lab1/grades").status_code == 403
    csv = server.http.get("/api/assignments/lab1/grades.csv")
    assert csv.status_code == 200 and csv.text.splitlines()[0].startswith("owner,project,status,runs,pan_overshoot")
    assert any(line.startswith(f"alice,{pid},completed,1.0,2.0") for line in csv.text.splitlines())
