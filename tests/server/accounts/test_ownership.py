"""The one ownership rule (server/security/ownership.py) through a real appliance, driven by the route
table: student A's project, build, run, logs, 3D recording and live stream exist, and student B

- gets, for every by-id route (path ids and body ids alike), exactly what a missing id gets:
  404 and the same body (a route with an id that is not classified here fails the test);
- finds none of A's things in any list or other GET route (every parameterless GET route of the
  app is called, so a new list that forgets the rule fails);
- cannot start A's build as a run of their own (404, as for a missing build), while A and an
  educator can;
- on the WebSocket, watching A's live run, receives state and the robot's motion but none of A's
  monitor lines, setpoint/Xeno2Ros names and values, build, project or name (the watch policy).
"""

from __future__ import annotations

import json
import re
import shutil
import time
import urllib.parse
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi.routing import APIRoute, APIWebSocketRoute
from test_route_table import permissions_of, walk

from xrf_testing.accounts_support import Account, make_account
from xrf_testing.harness import Server, shared_builds_root, start_server, stop_server
from xrf_testing.hostile import project_files
from xrf_testing.projects_support import reachable_tmp, targz
from xrflab.server.app import create_app
from xrflab.server.http.rerun import NO_LIVE_STREAM, SERVICE
from xrflab.server.security.auth import Perm
from xrflab.server.settings import Settings

REPO = Path(__file__).resolve().parents[3]

BASE = REPO / "student_projects" / "templates" / "base"
MISSING = 999_999  # an id nobody has

# By-id routes that serve a user's resource: (method, path) -> the id in the path that names it.
# Every other id is filled with A's own (the build of A's project, a file of A's run).
OWNED: dict[tuple[str, str], str] = {
    ("GET", "/api/runs/{run_id}"): "run_id",
    ("GET", "/api/logs/runs/{run_id}"): "run_id",
    ("GET", "/api/logs/runs/{run_id}/files/{name:path}"): "run_id",
    ("GET", "/api/logs/runs/{run_id}/viewer-link/{name:path}"): "run_id",
    ("GET", "/api/logs/runs/{run_id}/timing"): "run_id",
    ("GET", "/api/logs/runs/{run_id}/param-changes"): "run_id",
    ("GET", "/api/projects/{pid}"): "pid",
    ("DELETE", "/api/projects/{pid}"): "pid",
    ("GET", "/api/projects/{pid}/download"): "pid",
    ("GET", "/api/projects/{pid}/source"): "pid",
    ("PUT", "/api/projects/{pid}/source"): "pid",
    ("POST", "/api/projects/{pid}/builds"): "pid",
    ("GET", "/api/projects/{pid}/builds"): "pid",
    ("GET", "/api/projects/{pid}/builds/{bid}"): "pid",
    ("GET", "/api/projects/{pid}/builds/{bid}/log"): "pid",
    ("POST", "/api/projects/{pid}/builds/{bid}/run"): "pid",
    ("GET", "/api/projects/{pid}/files"): "pid",
    ("GET", "/api/projects/{pid}/files/{path:path}"): "pid",
    ("PUT", "/api/projects/{pid}/files/{path:path}"): "pid",
    ("DELETE", "/api/projects/{pid}/files/{path:path}"): "pid",
    ("GET", "/api/projects/{pid}/versions"): "pid",
    ("GET", "/api/projects/{pid}/diff"): "pid",
    ("GET", "/api/projects/{pid}/grade"): "pid",
    ("POST", "/api/projects/{pid}/grade"): "pid",
}
# By-id routes whose ids are not a user's resource, and why.
SHARED: dict[tuple[str, str], str] = {
    ("GET", "/api/assignments/{aid}/scenario"): "an assignment's scenario: the same for every student of it",
    ("PUT", "/api/assignments/{aid}/scenario"): "educators only",
    ("GET", "/api/assignments/{aid}/grades"): "educators only",
    ("POST", "/api/assignments/{aid}/grades/rerun"): "educators only",
    ("GET", "/api/assignments/{aid}/grades.csv"): "educators only",
    ("GET", "/api/project-templates/{template}/download"): "the bundled templates, everyone's",
    ("GET", "/rerun/{asset:path}"): "the rerun viewer's program files",
    ("GET", "/api/logs/viewer/{link}/{run_id}/{name:path}"): "the link in the path is the credential, one user's "
    "for one log (made by viewer-link, OWNED above); another run's, file's or a changed link is a 404: "
    "tests/logs/test_runs_logs.py _check_viewer_link",
    ("GET", "/api/params/{name:path}"): "the current run's parameter by name, every watcher's (issue 28)",
    ("GET", "/viser/{path:path}"): "the 3D view's client files (one scene for the room)",
    ("WS", "/viser/{path:path}"): "the 3D view's scene (one for the room: the robot's motion)",
    ("POST", f"/{SERVICE}/{{method}}"): "{method} is a gRPC method; the run is the live one: "
    "test_someone_elses_live_stream_is_no_stream",
}
# Routes naming a user's resource in their JSON body: (method, path) -> the body field.
BODY_IDS: dict[tuple[str, str], str] = {
    ("POST", "/api/runs"): "build",
    ("POST", "/api/viz/replay"): "run_id",
}
# Lists of a user's resources: each must hold A's for A and an educator, never for B.
LISTS = ("/api/runs", "/api/logs/runs", "/api/projects", "/api/viz/recordings")
# Bench-wide GET routes that name whoever drives, by design (security.md): who holds the bench
# is public; what they run is not. They are still checked for everything but the username.
NAMES_THE_DRIVER = {"/api/lease", "/api/ros"}
# Parameterless GET routes not called in the leak check, and why.
NOT_CALLED = {"/api/system/doctor": "runs the host checks (slow); reports the machine, no user data"}


def _route_table() -> list[tuple[str, str, Perm, Any]]:
    app = create_app(Settings(real_bench=False))
    out = []
    for route, inherited in walk(app.routes):
        if isinstance(route, (APIRoute, APIWebSocketRoute)):
            perm = permissions_of(route, inherited)[0]
            for method in sorted((getattr(route, "methods", None) or {"WS"}) - {"HEAD", "OPTIONS"}):
                out.append((method, route.path, perm, route))
    return out


ROUTES = _route_table()


# ---- the world: A's project, build and run --------------------------------------------------


@pytest.fixture(scope="module")
def server() -> Iterator[Server]:
    """Overrides conftest's: the data folder must be reachable by the build user (projects)."""
    data = reachable_tmp("ownership")
    s = start_server(data, shared_builds_root(), lease_idle_s=600.0)
    yield s
    stop_server(s)
    shutil.rmtree(data, ignore_errors=True)


@dataclass
class World:
    alice: Account
    bob: Account
    olga: Account  # an observer
    pid: int
    bid: int
    build: str  # the catalog name of A's build
    project_name: str
    run_id: int
    log_name: str

    def markers(self) -> tuple[str, ...]:
        """Strings that identify A's things: none may reach B."""
        return (self.project_name, self.build, self.alice.username)


def _wait_build(http: httpx.Client, pid: int, bid: int, timeout: float = 300) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while True:
        b = http.get(f"/api/projects/{pid}/builds/{bid}").json()
        if b["status"] not in ("queued", "building"):
            return b
        assert time.monotonic() < deadline, f"build {bid} still {b['status']}"
        time.sleep(0.2)


def _free(server: Server) -> None:
    server.stop_run()
    for _ in range(10):
        if server.http.get("/api/lease").json()["holder"] is None:
            return
        server.http.post("/api/lease/release")


def _to_run(ws: Any) -> None:
    ws.wait_state("IDLE", timeout=20)
    for cmd, state in (("initialise", "INITIALISED"), ("start", "RUN")):
        reply = ws.command(cmd)
        assert reply.get("accepted"), reply
        ws.wait_state(state)


@pytest.fixture(scope="module")
def world(server: Server) -> Iterator[World]:
    tag = uuid.uuid4().hex[:6]
    alice = make_account(server, f"own_alice_{tag}", "student")
    bob = make_account(server, f"own_bob_{tag}", "student")
    olga = make_account(server, f"own_olga_{tag}", "observer")
    name = f"secret-proj-{tag}"
    r = alice.http.post(
        "/api/projects",
        params={"name": name},
        files={"file": ("p.tar.gz", targz(project_files(BASE), "p"), "application/gzip")},
    )
    assert r.status_code == 201, r.text
    pid = r.json()["project"]["id"]
    r = alice.http.post(f"/api/projects/{pid}/builds")
    assert r.status_code == 201, r.text
    b = _wait_build(alice.http, pid, r.json()["id"])
    assert b["status"] == "ok", (b["result"], alice.http.get(f"/api/projects/{pid}/builds/{b['id']}/log").text[-6000:])
    _free(server)
    assert alice.http.post("/api/lease/take").status_code == 200
    with alice.ws() as ws:
        r = alice.http.post(f"/api/projects/{pid}/builds/{b['id']}/run", json={}, timeout=60)
        assert r.status_code == 201, r.text
        run = r.json()["run"]
        _to_run(ws)
        ws.wait_for(lambda m: m.get("type") == "monitor" and m.get("run_id") == run["id"], timeout=10)
    assert alice.http.post("/api/runs/current/stop", timeout=30).status_code == 200
    files = alice.http.get(f"/api/logs/runs/{run['id']}").json()["files"]
    assert files, "A's run has no log file to probe the download route with"
    _free(server)
    yield World(alice, bob, olga, pid, b["id"], f"project-{pid}-build-{b['id']}", name, run["id"], files[0]["name"])
    for a in (alice, bob, olga):
        a.http.close()


# ---- the route table ------------------------------------------------------------------------


def test_every_route_with_an_id_is_classified() -> None:
    """A new by-id route (or body id) must say whether it serves a user's resource."""
    unclassified = []
    for method, path, perm, route in ROUTES:
        if perm is Perm.EDUCATOR:
            continue  # students and observers never reach it
        if "{" in path and (method, path) not in OWNED and (method, path) not in SHARED:
            unclassified.append(f"{method} {path}")
        body = getattr(route, "body_field", None)
        model = body.field_info.annotation if body is not None else None
        if model is not None and hasattr(model, "model_fields"):
            ids = [f for f in model.model_fields if f in ("run_id", "pid", "project_id", "build", "build_id")]
            if ids and (method, path) not in BODY_IDS:
                unclassified.append(f"{method} {path} (body {ids})")
    assert not unclassified, "routes with ids not in OWNED/SHARED/BODY_IDS:\n" + "\n".join(unclassified)
    table = {(m, p) for m, p, _, _ in ROUTES}
    stale = (set(OWNED) | set(SHARED) | set(BODY_IDS)) - table
    assert not stale, f"classified routes that no longer exist: {stale}"
    assert set(BODY_IDS) <= {(m, p) for m, p, _, r in ROUTES if getattr(r, "body_field", None) is not None}


def _fill(path: str, w: World, key: str, ident: int) -> str:
    values = {
        "run_id": w.run_id,
        "pid": w.pid,
        "bid": w.bid,
        "name:path": w.log_name,
        "path:path": "CMakeLists.txt",
        key: ident,
    }
    filled = re.sub(r"\{([^}]+)\}", lambda m: urllib.parse.quote(str(values[m.group(1)]), safe="/"), path)
    query = {"/source": "?path=CMakeLists.txt", "/diff": "?a=1"}
    return filled + next((q for end, q in query.items() if path.endswith(end)), "")


def _request(http: httpx.Client, method: str, url: str) -> httpx.Response:
    kw: dict[str, Any] = {"json": {}} if method == "POST" else {}
    if method == "PUT":
        kw = {"content": b"", "headers": {"content-type": "application/gzip"}}
    return http.request(method, url, timeout=60, **kw)


def _same_answer(theirs: httpx.Response, their_id: Any, missing: httpx.Response, missing_id: Any) -> None:
    """Status and body identical once the id itself is blanked out."""

    def norm(r: httpx.Response, ident: Any) -> str:
        return re.sub(rf"(?<![0-9A-Za-z_-]){re.escape(str(ident))}(?![0-9A-Za-z_])", "<id>", r.text)

    assert theirs.status_code == 404, (theirs.status_code, theirs.text)
    assert missing.status_code == 404, (missing.status_code, missing.text)
    assert norm(theirs, their_id) == norm(missing, missing_id), (theirs.text, missing.text)
    assert theirs.headers.get("content-type") == missing.headers.get("content-type")


def test_someone_elses_id_answers_as_a_missing_one(server: Server, world: World) -> None:
    w = world
    _free(server)
    assert w.bob.http.post("/api/lease/take").status_code == 200  # so DRIVE routes reach the rule
    try:
        for (method, path), key in OWNED.items():
            ident = {"run_id": w.run_id, "pid": w.pid}[key]
            mine, missing = _fill(path, w, key, ident), _fill(path, w, key, MISSING)
            if method == "GET":  # the id is real: its owner and an educator get it
                for who, http in (("owner", w.alice.http), ("educator", server.http)):
                    r = http.get(mine, timeout=60)
                    assert r.status_code == 200, (who, mine, r.status_code, r.text[:300])
            for who, http in (("student", w.bob.http), ("observer", w.olga.http)):
                if method != "GET" and who == "observer":
                    continue  # observers are refused these by their role (403) before any id
                r_mine, r_missing = _request(http, method, mine), _request(http, method, missing)
                if who == "observer" and r_mine.status_code == 403:
                    # Refused by the role (observers have no projects) before any id is looked at:
                    # the same answer for a real id and a missing one, so nothing is learnt.
                    assert (r_missing.status_code, r_missing.text) == (403, r_mine.text), (mine, r_missing.text)
                    continue
                _same_answer(r_mine, ident, r_missing, MISSING)
        # ids in a body: replaying A's run in the 3D view
        r = w.bob.http.post("/api/viz/replay", json={"run_id": w.run_id})
        _same_answer(r, w.run_id, w.bob.http.post("/api/viz/replay", json={"run_id": MISSING}), MISSING)
    finally:
        _free(server)
    # ... which A may replay (the recording exists)
    assert w.alice.http.post("/api/lease/take").status_code == 200
    try:
        r = w.alice.http.post("/api/viz/replay", json={"run_id": w.run_id})
        assert r.status_code == 200, r.text
        w.alice.http.post("/api/viz/live")
    finally:
        _free(server)
    assert server.http.get(_fill("/api/projects/{pid}", w, "pid", w.pid)).status_code == 200  # B deleted nothing


def test_lists_are_filtered(server: Server, world: World) -> None:
    w = world
    want = {
        "/api/runs": ("id", w.run_id),
        "/api/logs/runs": ("id", w.run_id),
        "/api/projects": ("id", w.pid),
        "/api/viz/recordings": ("run_id", w.run_id),
    }
    assert set(want) == set(LISTS)
    for path, (field, ident) in want.items():
        query = "?all=true" if path == "/api/projects" else ""  # an educator's default is their own
        for who, http, sees in (
            ("owner", w.alice.http, True),
            ("educator", server.http, True),
            ("student", w.bob.http, False),
            ("observer", w.olga.http, False),
        ):
            r = http.get(path + query)
            if path == "/api/projects" and who == "observer":
                assert r.status_code == 403  # no projects at all
                continue
            assert r.status_code == 200, (who, path, r.text)
            ids = [item[field] for item in r.json()]
            assert (ident in ids) is sees, (who, path, ids)


def test_no_get_route_shows_b_anything_of_a(server: Server, world: World) -> None:
    """Every parameterless GET route of the app, as B and as an observer: none of A's project
    name, build name or username (the lease and ROS status name whoever drives, by design)."""
    w = world
    called = 0
    for method, path, perm, _ in ROUTES:
        if method != "GET" or "{" in path or perm is Perm.EDUCATOR or path in NOT_CALLED:
            continue
        for http in (w.bob.http, w.olga.http):
            r = http.get(path, params={"all": "true"} if path == "/api/projects" else None, timeout=60)
            called += 1
            markers = w.markers()[:2] if path in NAMES_THE_DRIVER else w.markers()
            leaked = [m for m in markers if m in r.text]
            assert not leaked, f"GET {path} shows {leaked}: {r.text[:300]}"
    assert called > 20
    # the check can fail: an educator's lists do hold A's things
    assert all(
        m in server.http.get("/api/runs").text + server.http.get("/api/projects?all=true").text for m in w.markers()
    )


def test_someone_elses_live_stream_is_no_stream(server: Server, world: World) -> None:
    w = world
    mine = w.alice.http.get("/api/logs/rerun").json()
    if mine["live_run"] is None:
        pytest.skip(f"no live rerun stream on this machine: {mine['live_reason']}")
    assert mine["live_run"] == w.run_id and mine["live_allowed"]
    theirs = w.bob.http.get("/api/logs/rerun").json()
    assert theirs["live_run"] is None and theirs["live_url"] == "" and theirs["live_reason"] == NO_LIVE_STREAM
    r = w.bob.http.post(
        f"/{SERVICE}/ReadMessages", content=b"\0" * 5, headers={"content-type": "application/grpc-web+proto"}
    )
    assert r.status_code == 404 and r.headers["grpc-status"] == "5", (r.status_code, r.headers)
    assert urllib.parse.unquote(r.headers["grpc-message"]) == NO_LIVE_STREAM


# ---- starting someone else's build ----------------------------------------------------------


def test_someone_elses_build_cannot_be_run(server: Server, world: World) -> None:
    w = world
    _free(server)
    assert w.bob.http.post("/api/lease/take").status_code == 200
    try:
        theirs = w.bob.http.post("/api/runs", json={"build": w.build}, timeout=60)
        for missing_name in (f"project-{MISSING}-build-{w.bid}", "no-such-build"):
            missing = w.bob.http.post("/api/runs", json={"build": missing_name}, timeout=60)
            assert theirs.status_code == missing.status_code == 404, (theirs.text, missing.text)
            assert theirs.text.replace(w.build, "<b>") == missing.text.replace(missing_name, "<b>")
        assert server.http.get("/api/status").json()["run_active"] is False
        refused = server.http.get("/api/audit", params={"username": w.bob.username, "action": "run.start_failed"})
        assert any(e["detail"].get("build") == w.build for e in refused.json()), refused.text
    finally:
        _free(server)
    # its owner may (and the run is hers), and so may an educator
    for who, http in (("owner", w.alice.http), ("educator", server.http)):
        if who == "owner":
            assert http.post("/api/lease/take").status_code == 200
        r = http.post("/api/runs", json={"build": w.build, "max_cycles": 50}, timeout=60)
        assert r.status_code == 201, (who, r.text)
        _free(server)


# ---- the WebSocket: what others may watch of the live run -------------------------------------


def _collect(ws: Any, seconds: float) -> None:
    """Keep receiving for `seconds` (messages land in ws.messages)."""
    with pytest.raises(AssertionError):
        ws.wait_for(lambda m: False, timeout=seconds)


def test_watchers_see_state_and_motion_but_not_the_owners_output(server: Server, world: World) -> None:
    w = world
    _free(server)
    assert w.alice.http.post("/api/lease/take").status_code == 200
    try:
        with w.alice.ws() as wa, w.bob.ws() as wb, w.olga.ws() as wo, server.ws() as we:
            r = w.alice.http.post(f"/api/projects/{w.pid}/builds/{w.bid}/run", json={}, timeout=60)
            assert r.status_code == 201, r.text
            run_id = r.json()["run"]["id"]
            _to_run(wa)
            wa.send({"type": "setpoint", "fields": {"steer_left": 0.05}})
            assert wa.wait_type("ack")["setpoint"]["steer_left"] == 0.05

            def monitor(m: dict[str, Any]) -> bool:
                return (
                    m.get("type") == "monitor"
                    and m.get("run_id") == run_id
                    and any("run: enc" in line["text"] for line in m["lines"])
                )

            def named_signals(m: dict[str, Any]) -> bool:
                return (
                    m.get("type") == "telemetry"
                    and m.get("run_id") == run_id
                    and all("pos_left" in sample["xeno2ros"] for sample in m["samples"])
                )

            for ws in (wa, we):  # the owner and an educator: everything
                ws.wait_for(monitor, timeout=10, seen=True)
                ws.wait_for(named_signals, timeout=10, seen=True)
                started = ws.wait_type("run", seen=True, event="started")
                assert started["run"]["build"] == w.build and "steer_left" in json.dumps(started["ros2xeno"])
            for ws in (wb, wo):  # another student, an observer: state and motion
                ws.wait_state("RUN", timeout=10)
                ws.wait_for(
                    lambda m: (
                        m.get("type") == "telemetry"
                        and m.get("run_id") == run_id
                        and all(len(sample["enc"]) > 0 and "pwm" in sample for sample in m["samples"])
                    ),
                    timeout=10,
                    seen=True,
                )
            with w.bob.ws() as late:  # a watcher who connects mid-run gets the public snapshot
                snap = late.wait_type("run", seen=True)
                assert snap["run"]["id"] == run_id and snap["redacted"] and snap["run"]["build"] == ""
                assert snap["ros2xeno"] == [] and snap["xeno2ros"] == [] and snap["setpoint"] == {}
                assert snap["channels"] == 4  # the bench's, like the telemetry it sizes: everyone's
                assert late.wait_type("state", seen=True)["name"] == "RUN"
                _collect(late, 1.0)
                watched = [*late.messages]
            _collect(wb, 1.5)  # the monitor prints at 2 Hz: several lines pass B by
            w.alice.http.post("/api/runs/current/stop", timeout=30)
            for ws in (wb, wo):
                ws.wait_type("run", event="ended", timeout=10)
                watched += ws.messages
    finally:
        _free(server)
    assert any(m.get("type") == "state" and m.get("name") == "RUN" for m in watched)
    assert not [m for m in watched if m.get("type") == "monitor"], "monitor lines reached a watcher"
    for m in watched:
        if m.get("type") == "telemetry":
            assert m["ros2xeno"] == {}, m  # the setpoints are the owner's too
            assert m["samples"] and all(sample["xeno2ros"] == {} for sample in m["samples"]), m
        if m.get("type") == "run":
            assert m["redacted"] and m["run"]["build"] == "" and m["run"]["owner"] == "" and m["run"]["run_dir"] == ""
        text = json.dumps(m)
        markers = w.markers()[:2] if m.get("type") in ("lease", "ros") else w.markers()
        leaked = [s for s in (*markers, "steer_left", "pos_left", "run: enc") if s in text]
        assert not leaked, (leaked, m)
