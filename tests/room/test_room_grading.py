"""The room's grading table across two benches (issue 32): a real mosquitto (TLS), a real room and
two real appliances enrolled with `xrf room join`. The educator publishes the jiwy example as an
assignment and its scenario in the room (a broken one refused with its line); each student builds
their copy on their own bench; "re-run on all latest builds" has every bench grade its own
students' builds; the room's one table shows both students, with the bench each row came from,
links to that bench (its enrolled address) and the CSV across the room. A bench's login cannot
put rows under another bench's name, and what it sends that does not fit is dropped, counted. The
page: the table in Debian's chromium."""

from __future__ import annotations

import csv
import io
import math
import shutil
import time
from collections.abc import Iterator
from typing import Any

import httpx
import pytest

from xrf_testing.harness import REPO_ROOT, login_client, wait_for
from xrf_testing.projects_support import build_and_wait, reachable_tmp, targz
from xrf_testing.room_support import TEACHER, TEACHER_PW, Lab, as_bench, room_lab, sent
from xrflab.room import topics

pytestmark = pytest.mark.live

JIWY = REPO_ROOT / "student_projects" / "examples" / "jiwy"
SCENARIO = (REPO_ROOT / "student_projects" / "scenarios" / "jiwy.toml").read_text()
STUDENTS = {"s1": "student-one-pw-123", "s2": "student-two-pw-123"}
HOME = {"s1": 1, "s2": 2}  # the bench each student works on


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Lab]:
    benches = reachable_tmp("room-grading")  # the build user compiles in a bench's data folder
    try:
        with room_lab(tmp_path_factory.mktemp("room-grading"), 2, benches) as lab:
            for name, pw in STUDENTS.items():
                r = lab.teacher.post(
                    "/api/users", json={"username": name, "role": "student", "password": pw, "must_change": False}
                )
                assert r.status_code == 201, r.text
            wait_for(lambda: lab.online() == {"b1", "b2"}, 20, "2 benches online")
            yield lab
    finally:
        shutil.rmtree(benches, ignore_errors=True)


def student(lab: Lab, name: str) -> httpx.Client:
    """`name` logged in on their bench once the room's class list reached it (few attempts, spaced:
    5 failed logins lock the account there)."""
    url = lab.benches[HOME[name] - 1].url

    def attempt() -> httpx.Client | None:
        try:
            return login_client(url, name, STUDENTS[name])
        except AssertionError:
            time.sleep(1.5)  # the point: spaced, or 5 failures lock the account on that bench
            return None

    return wait_for(attempt, 10, f"{name} accepted on b{HOME[name]}")


def table(lab: Lab, aid: str) -> dict[str, Any]:
    r = lab.teacher.get(f"/api/room/assignments/{aid}/grades")
    assert r.status_code == 200, r.text
    return r.json()


def completed(t: dict[str, Any]) -> dict[tuple[str, str], dict[str, Any]]:
    return {(r["owner"], r["bench"]): r for r in t["rows"] if r["status"] == "completed"}


@pytest.fixture(scope="module")
def graded(lab: Lab) -> dict[str, Any]:
    """The assignment published, its scenario kept, each student's copy built on their bench and
    everything re-run from the room: the room's table once both benches are through."""
    files = {
        str(p.relative_to(JIWY)): p.read_bytes() for p in JIWY.rglob("*") if p.is_file() and "build" not in p.parts
    }
    r = lab.teacher.post("/api/room/assignments/upload", params={"name": "Jiwy PID"}, content=targz(files, "jiwy"))
    assert r.status_code == 201, r.text
    aid = r.json()["id"]

    # a scenario with a TOML error is refused with its line; the room keeps none
    broken = SCENARIO.replace("[scenario]", "[scenario", 1)
    r = lab.teacher.put(f"/api/room/assignments/{aid}/scenario", content=broken.encode())
    assert r.status_code == 422, r.text
    assert r.json()["detail"]["line"] == broken.splitlines().index("[scenario") + 1, r.text
    assert lab.teacher.get(f"/api/room/assignments/{aid}/scenario").status_code == 404
    r = lab.teacher.put(f"/api/room/assignments/{aid}/scenario", content=SCENARIO.encode())
    assert r.status_code == 200, r.text
    checks = r.json()["checks"]

    def on_both() -> bool:
        got = {b for a in lab.teacher.get("/api/room/assignments").json() if a["id"] == aid for b in a["benches"]}
        return got == {"b1", "b2"}

    wait_for(on_both, 30, "the assignment on b1 and b2")
    pids = {}
    for name in STUDENTS:
        c = student(lab, name)
        pid = next(p["id"] for p in c.get("/api/projects").json() if p["origin"] == f"assignment:{aid}")
        b = build_and_wait(c, pid)
        assert b["status"] == "ok", b["result"]
        pids[name] = pid
        c.close()

    r = lab.teacher.post(f"/api/room/assignments/{aid}/grades", json={"rerun": True})
    assert r.status_code == 202, r.text
    assert r.json()["benches"] == ["b1", "b2"] and r.json()["scenario"] is True
    t0 = time.monotonic()

    def through() -> dict[str, Any] | None:
        t = table(lab, aid)
        p = t["progress"]
        done = p["total"] > 0 and p["done"] == p["total"]
        return t if done and set(completed(t)) >= {("s1", "b1"), ("s2", "b2")} else None

    t = wait_for(through, 120, "both benches graded their students")
    print(f"room re-run across 2 benches: {time.monotonic() - t0:.1f} s to the full table")
    return {"aid": aid, "table": t, "pids": pids, "checks": checks}


def test_the_room_table_across_two_benches(lab: Lab, graded: dict[str, Any]) -> None:
    t, aid = graded["table"], graded["aid"]
    assert [c["id"] for c in t["checks"]] == graded["checks"]
    assert set(t["benches"]) == {"b1", "b2"}
    for name, b in t["benches"].items():
        assert b["answered"] and not b["error"] and b["same_checks"], (name, b)
    rows = completed(t)
    for name, i in HOME.items():
        r = rows[(name, f"b{i}")]
        bench = lab.benches[i - 1]
        # each row is the student's own project on their own bench, graded from its latest build there
        assert r["project"] == graded["pids"][name]
        assert r["build"].startswith(f"project-{graded['pids'][name]}-build-"), r
        assert set(r["checks"]) == set(graded["checks"])
        # the example is a correct controller: every check passes, with every point
        assert all(c["passed"] for c in r["checks"].values()), r["checks"]
        assert r["earned"] == r["points"] > 0 and math.isclose(
            sum(c["earned"] for c in r["checks"].values()), r["earned"]
        )
        # links to the bench the row came from (its enrolled address), its run's log there
        assert r["plots"] == f"{bench.url}/#grades"
        assert r["log"] == f"{bench.url}/api/logs/runs/{r['run']}"
        log = bench.http.get(f"/api/logs/runs/{r['run']}")
        assert log.status_code == 200 and log.json()["run"]["owner"] == name and log.json()["files"], log.text[:300]
    # the other student's copy on each bench has no build there: a row saying so, 0 points
    for r in t["rows"]:
        if (r["owner"], r["bench"]) not in rows:
            assert r["status"] == "build_failed" and r["earned"] == 0, r

    text = lab.teacher.get(f"/api/room/assignments/{aid}/grades.csv").text
    got = list(csv.DictReader(io.StringIO(text)))
    assert got and list(got[0])[:4] == ["owner", "bench", "project", "status"]
    by = {(g["owner"], g["bench"]): g for g in got}
    for name, i in HOME.items():
        g = by[(name, f"b{i}")]
        assert float(g["total"]) == rows[(name, f"b{i}")]["earned"] and g["status"] == "completed"
        assert all(float(g[c]) > 0 for c in graded["checks"] if rows[(name, f"b{i}")]["checks"][c]["earned"] > 0)

    # only educators
    s1 = login_client(lab.room.url, "s1", STUDENTS["s1"])
    for method, path in (
        ("GET", f"/api/room/assignments/{aid}/grades"),
        ("POST", f"/api/room/assignments/{aid}/grades"),
        ("GET", f"/api/room/assignments/{aid}/grades.csv"),
        ("PUT", f"/api/room/assignments/{aid}/scenario"),
    ):
        assert s1.request(method, path, json={}).status_code == 403, path
    s1.close()


def test_a_bench_cannot_write_another_benchs_rows(lab: Lab, graded: dict[str, Any]) -> None:
    """With b1's broker login (read from its enrolment file): a table under b2's topic never reaches
    the room (the broker's ACL), one under b1's own shows as b1's rows only and lasts until b1's
    next; an oversized, a wrong-typed or a foreign assignment's table is dropped and counted."""
    aid = graded["aid"]
    before = table(lab, aid)
    b2_rows = [r for r in before["rows"] if r["bench"] == "b2"]
    dropped0 = lab.views()["b1"]["dropped"]
    forged = {
        "boot": time.time_ns() // 1_000_000 + 60_000,
        "seq": 10**9,
        "t": time.time(),
        "assignment": aid,
        "checks": [{"id": c, "kind": "bound", "points": 1.0} for c in graded["checks"]],
        "rows": [
            {"project": graded["pids"]["s2"], "owner": "s2", "status": "completed", "earned": 99.0, "points": 99.0}
        ],
    }
    attacker = as_bench(lab, 0)
    try:
        attacker.publish(topics.bench("b2", "grades"), forged)  # the ACL: b1 writes only under b1
        sent(attacker, topics.bench("b1", "grades"), forged)
        wait_for(
            lambda: any(r["earned"] == 99.0 for r in table(lab, aid)["rows"] if r["bench"] == "b1"), 10, "b1's forgery"
        )
        after = table(lab, aid)
        assert [r for r in after["rows"] if r["bench"] == "b2"] == b2_rows  # b2's rows are b2's
        bad = (
            {**forged, "seq": 10**9 + 1, "rows": [{**forged["rows"][0], "earned": "99"}]},  # a string for a number
            {**forged, "seq": 10**9 + 2, "assignment": "nosuch"},  # not an assignment of the room
            {**forged, "seq": 10**9 + 3, "error": "x" * (600 << 10)},  # over 512 KB
        )
        for m in bad:
            sent(attacker, topics.bench("b1", "grades"), m)
        wait_for(lambda: lab.views()["b1"]["dropped"] >= dropped0 + 3, 10, "3 dropped")
    finally:
        attacker.close()
    # b1's own next table replaces the forged one (another boot: the forgery cannot hold it off)
    assert lab.teacher.post(f"/api/room/assignments/{aid}/grades", json={"rerun": False}).status_code == 202
    real = completed(graded["table"])[("s1", "b1")]["earned"]
    wait_for(
        lambda: (
            completed(table(lab, aid)).get(("s1", "b1"), {}).get("earned") == real
            and not any(r["earned"] == 99.0 for r in table(lab, aid)["rows"])
        ),
        15,
        "b1's real table back",
    )


def test_the_room_page_shows_the_table(lab: Lab, graded: dict[str, Any], chromium_path: str) -> None:
    from playwright.sync_api import sync_playwright

    from xrf_testing.harness import CHROMIUM_ARGS

    aid = graded["aid"]
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium_path, args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1366, "height": 768})
        page.goto(lab.room.url + "/")
        page.fill("#login-user", TEACHER)
        page.fill("#login-pass", TEACHER_PW)
        page.click("#login-submit")
        page.wait_for_selector(f"[data-assignment='{aid}'] button.grades")
        page.click(f"[data-assignment='{aid}'] button.grades")
        for name, i in HOME.items():
            page.wait_for_selector(f"#room-grades-table tr[data-bench='b{i}'][data-owner='{name}']", timeout=15000)
        row = page.locator("#room-grades-table tr[data-bench='b1'][data-owner='s1']")
        expected = completed(table(lab, aid))[("s1", "b1")]
        assert f"{expected['earned']:g} / {expected['points']:g}" in row.locator("td.total").inner_text()
        assert row.locator("td.pass").count() == len(graded["checks"])
        assert row.locator("a", has_text="log").get_attribute("href") == expected["log"]
        # re-run from the page: progress across the room, then both rows again
        page.click("#room-grades-rerun")
        page.wait_for_function("document.getElementById('room-note').textContent.includes('re-run asked of b1, b2')")
        page.wait_for_function(
            "(() => { const p = document.querySelector('#room-grades-progress progress');"
            " return p && p.value === p.max; })()",
            timeout=60000,
        )
        assert page.get_attribute("#room-grades-csv", "href") == f"/api/room/assignments/{aid}/grades.csv"
        assert "b1:" in page.inner_text("#room-grades-benches") and "b2:" in page.inner_text("#room-grades-benches")
        browser.close()
