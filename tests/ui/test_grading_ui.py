"""The grading pages in Debian's chromium (issue 32): three students' copies of an assignment with a
scenario; one checks hers on the Editor page (results per check, plots with their bounds), the
educator re-runs all from the Grades page and sees the student x check table and its CSV."""

from __future__ import annotations

import hashlib
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest

from xrf_testing.harness import (
    UNCONFINED_UNLESS_ROOT,
    Server,
    browser_login,
    shared_builds_root,
    start_server,
    stop_server,
)
from xrf_testing.projects_support import build_and_wait, reachable_tmp, targz
from xrflab.projects.assignments import Assignments

REPO = Path(__file__).resolve().parents[2]
SCENARIO = (REPO / "student_projects" / "scenarios" / "jiwy.toml").read_text()


def _install_assignment(data_dir: Path) -> None:
    """The Jiwy example as assignment lab1, as the room would have published it."""
    jiwy = REPO / "student_projects" / "examples" / "jiwy"
    files = {
        str(p.relative_to(jiwy)): p.read_bytes() for p in jiwy.rglob("*") if p.is_file() and "build" not in p.parts
    }
    archive = data_dir / "jiwy.tar.gz"
    archive.write_bytes(targz(files, "jiwy"))
    digest = hashlib.sha256(archive.read_bytes()).hexdigest()
    Assignments(data_dir / "assignments").install({"id": "lab1", "name": "Lab 1", "sha256": digest}, archive)
    archive.unlink()


pytestmark = pytest.mark.live
STUDENTS = ("alice", "bob", "carol")


@pytest.fixture(scope="module")
def server() -> Iterator[Server]:
    data = reachable_tmp("grading-ui")  # the build user must reach the projects
    try:
        _install_assignment(data)
        srv = start_server(data, shared_builds_root(), allow_unconfined=UNCONFINED_UNLESS_ROOT)  # harness.py says why
        try:
            yield srv
        finally:
            stop_server(srv)
    finally:
        shutil.rmtree(data, ignore_errors=True)


def test_three_students_check_and_the_educator_table(server: Server, raw_browser, browser) -> None:
    assert server.http.put("/api/assignments/lab1/scenario", content=SCENARIO.encode()).status_code == 200
    pids, passwords = {}, {}
    for name in STUDENTS:
        passwords[name] = server.create_user(name)
        http, _ = server.login(name, passwords[name])
        pid = next(p["id"] for p in http.get("/api/projects").json() if p["origin"] == "assignment:lab1")
        assert build_and_wait(http, pid)["status"] == "ok"
        pids[name] = pid

    # A student: Check my project on the Editor page.
    ctx = raw_browser.new_context()
    page = ctx.new_page()
    try:
        browser_login(page, server.url, "alice", passwords["alice"])
        page.goto(server.url + "/#editor")
        page.wait_for_function("window.xrfEditor && window.xrfEditor.ready")
        page.evaluate(f"window.xrfEditor.open({pids['alice']})")
        page.wait_for_selector("#gr-panel:not(.hidden)", timeout=20_000)
        page.click("#gr-check")
        page.wait_for_selector(".gr-check", timeout=90_000)
        assert page.locator(".gr-check").count() == 5
        assert "/ " in page.inner_text(".gr-total")
        assert page.locator(".gr-check svg.gr-plot").count() >= 3
        assert page.locator(".gr-check svg .gr-bound").count() >= 1  # a bound drawn on a plot
        page.click("#gr-check")  # again at once: rate-limited, said in words
        page.wait_for_function("document.getElementById('gr-msg').textContent.includes('again in')")
    finally:
        ctx.close()

    # The educator: the Grades page, re-run all, the table, the CSV.
    ed = browser.new_page()
    try:
        ed.goto(server.url + "/#grades")
        ed.wait_for_selector("#gr-assignment option", state="attached")
        ed.click("#gr-rerun")
        ed.wait_for_function(
            "(() => { const p = document.querySelector('#gr-progress progress');"
            " return p && p.value === p.max && p.max >= 3"
            " && document.querySelectorAll('#gr-table tbody tr[data-project]').length === 3; })()",
            timeout=240_000,
        )
        rows = ed.locator("#gr-table tbody tr[data-project]")
        assert rows.count() == 3
        owners = sorted(rows.nth(i).locator("td").first.inner_text() for i in range(3))
        assert owners == list(STUDENTS)
        assert ed.locator("#gr-table thead th").count() == 3 + 5 + 2
        assert ed.locator("#gr-table td.pass").count() > 0
        href = ed.get_attribute("#gr-csv", "href")
        csv = server.http.get(href)
        assert csv.status_code == 200 and len(csv.text.strip().splitlines()) == 4
        ed.locator(".gr-open").first.click()
        ed.wait_for_selector("#gr-detail .gr-check")
    finally:
        ed.context.close()
