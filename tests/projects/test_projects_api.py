"""Projects through the real appliance: upload, build (output streamed over the WebSocket), run
to RUN, reuse, refusals, clickable errors, 20-sim frequency, a message change reaching the
codec and the run's setpoint fields, owners kept apart, and `xrf upload`."""

from __future__ import annotations

import io
import os
import subprocess
import sys
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from xrf_testing import hostile
from xrf_testing.harness import Server, shared_builds_root, start_server, stop_server
from xrf_testing.projects_support import build_and_wait, targz

REPO = Path(__file__).resolve().parents[2]
BASE = REPO / "student_projects/templates/base"
TWENTY = REPO / "student_projects/templates/20sim"


@pytest.fixture(scope="module")
def server(module_data_dir: Path) -> Iterator[Server]:
    s = start_server(module_data_dir, shared_builds_root())
    yield s
    stop_server(s)


def upload(http, data: bytes, name: str = "proj.tar.gz", pid: int | None = None):  # noqa: ANN001, ANN201
    files = {"file": (name, data, "application/gzip")}
    return http.put(f"/api/projects/{pid}/source", files=files) if pid else http.post("/api/projects", files=files)


def run_to_run(server: Server, http, ws, pid: int, bid: int) -> dict:  # noqa: ANN001
    r = http.post(f"/api/projects/{pid}/builds/{bid}/run", json={}, timeout=60)
    assert r.status_code == 201, r.text
    run = r.json()["run"]
    ws.wait_state("IDLE", timeout=20)
    for cmd, state in (("initialise", "INITIALISED"), ("start", "RUN")):
        assert ws.command(cmd)["accepted"], cmd
        ws.wait_state(state)
    return run


def test_template_uploaded_built_and_run(server: Server) -> None:
    server.stop_run()
    ws = server.ws()
    ws.send({"type": "subscribe", "topics": ["build", "state", "run"]})
    r = upload(server.http, targz(hostile.project_files(BASE), "my_base"), "my_base.tar.gz")
    assert r.status_code == 201, r.text
    up = r.json()
    pid = up["project"]["id"]
    assert up["stripped_folder"] == "my_base" and up["project"]["name"] == "my_base"
    b = build_and_wait(server.http, pid)
    assert b["status"] == "ok", b["result"]
    assert b["runnable"] and b["toolchain"].startswith("cmake version")
    # the output came over the WebSocket, line by line, then the final status
    ws.wait_for(
        lambda m: m.get("type") == "build" and m.get("build_id") == b["id"] and m.get("status") == "ok",
        timeout=10,
        seen=True,
    )
    lines = [
        m["line"] for m in ws.messages if m.get("type") == "build" and m.get("build_id") == b["id"] and "line" in m
    ]
    assert any("Linking CXX executable" in ln for ln in lines)
    log = server.http.get(f"/api/projects/{pid}/builds/{b['id']}/log").text
    assert "sandbox: no network" in log

    run = run_to_run(server, server.http, ws, pid, b["id"])
    assert run["build"] == f"project-{pid}-build-{b['id']}"
    detail = server.http.get(f"/api/projects/{pid}").json()
    assert {"run_id": run["id"], "build_id": b["id"]} in detail["runs"]
    assert server.http.get(f"/api/runs/{run['id']}").json()["build"] == run["build"]
    server.stop_run()

    # unchanged: the same build comes back at once
    t0 = time.monotonic()
    again = server.http.post(f"/api/projects/{pid}/builds").json()
    assert again["reused"] and again["id"] == b["id"] and time.monotonic() - t0 < 2
    ws.close()


def test_hostile_uploads_refused_and_nothing_left(server: Server) -> None:
    root = server.data_dir / "projects"
    server.http.get("/api/projects")  # the service exists
    before = sorted(p.name for p in root.iterdir())
    for maker, entry in (
        (hostile.traversal_tar, "../../etc/x"),
        (hostile.symlink_tar, "src/root"),
        (hostile.device_tar, "src/null"),
        (hostile.no_cmakelists, "CMakeLists.txt"),
        (hostile.zip_bomb_declared, "data/zeros.bin"),
        (hostile.two_gb_file, "data/recording.bin"),
    ):
        r = upload(server.http, maker(), "x.tar.gz")
        assert r.status_code == 422, (maker.__name__, r.status_code, r.text)
        d = r.json()["detail"]
        assert d["entry"] == entry or entry in d["entry"], (maker.__name__, d)
        assert d["error"].startswith("archive refused: ")
    assert sorted(p.name for p in root.iterdir()) == before
    assert not any((root / ".incoming").iterdir())
    assert not Path("/etc/x").exists()


def test_compile_error_clickable_source(server: Server) -> None:
    files = hostile.project_files(BASE)
    text = files["src/Template.cpp"].decode().splitlines()
    text.insert(10, "int broken = undefined_name_here;")
    files["src/Template.cpp"] = ("\n".join(text) + "\n").encode()
    pid = upload(server.http, targz(files)).json()["project"]["id"]
    b = build_and_wait(server.http, pid)
    assert b["status"] == "failed" and b["result"].startswith("src/Template.cpp:11:"), b["result"]
    d = b["details"]["diagnostics"][0]
    ex = server.http.get(f"/api/projects/{pid}/source", params={"path": d["file"], "line": d["line"]}).json()
    assert ex["highlight"] == 11 and ex["lines"][11 - ex["first"]] == "int broken = undefined_name_here;"
    for bad in ("../../../../etc/passwd", "/etc/passwd", "src/../../x"):
        r = server.http.get(f"/api/projects/{pid}/source", params={"path": bad})
        assert r.status_code in (400, 404), (bad, r.status_code)
    assert server.http.post(f"/api/projects/{pid}/builds/{b['id']}/run", json={}).status_code == 409


def test_20sim_project_builds_with_its_step_size(server: Server) -> None:
    files = hostile.project_files(TWENTY)
    for k in list(files):
        if "LoopController" in k:
            v = files.pop(k).decode()
            v = v.replace("LoopController", "PanTilt").replace("<![CDATA[0.001]]>", "<![CDATA[0.0025]]>")
            v = v.replace("m_step_size = 0.001;", "m_step_size = 0.0025;").replace(
                "Step size:   0.001", "Step size:   0.0025"
            )
            files[k.replace("LoopController", "PanTilt")] = v.encode()
        elif k.endswith((".cpp", ".hpp", ".h", ".txt")):
            files[k] = files[k].decode().replace("LoopController", "PanTilt").encode()
    pid = upload(server.http, targz(files, "pan_tilt")).json()["project"]["id"]
    info = server.http.get(f"/api/projects/{pid}").json()["twenty_sim"]
    assert info["submodel"] == "PanTilt" and info["time_step_size"] == 0.0025 and info["frequency_hz"] == 400
    assert info["integration_method"] == "Euler"
    assert info["inputs"] == ["SetPoint1", "Position1", "SetPoint2", "Position2"]
    assert info["outputs"] == ["Steer1", "Steer2"]
    b = build_and_wait(server.http, pid)
    assert b["status"] == "ok", b["result"]
    assert b["details"]["twenty_sim"]["frequency_hz"] == 400
    assert b["details"]["cycle_freq"] == 400
    server.stop_run()
    with server.ws() as ws:
        run = run_to_run(server, server.http, ws, pid, b["id"])
        assert server.http.get(f"/api/runs/{run['id']}").json()["cycle_freq"] == 400
    server.stop_run()


def test_message_change_reaches_codec_and_setpoints(server: Server) -> None:
    from xrflab.msgdef import Codec

    files = hostile.project_files(BASE)
    pid = upload(server.http, targz(files)).json()["project"]["id"]
    old = files["msg/Ros2Xeno.msg"].decode()
    assert "steer_left" in old
    files["msg/Ros2Xeno.msg"] = old.replace("steer_left", "wheel_speed_left").encode()
    files["src/Template.cpp"] = (
        files["src/Template.cpp"].decode().replace("ros_msg.steer_left", "ros_msg.wheel_speed_left").encode()
    )
    r = upload(server.http, targz(files), pid=pid)
    assert r.status_code == 200, r.text
    msgs = server.http.get(f"/api/projects/{pid}").json()["messages"]
    assert "wheel_speed_left" in [f["name"] for f in msgs["Ros2Xeno"]]
    b = build_and_wait(server.http, pid)
    assert b["status"] == "ok", b["result"]
    server.stop_run()
    with server.ws() as ws:
        ws.send({"type": "subscribe", "topics": ["state", "run"]})
        run = run_to_run(server, server.http, ws, pid, b["id"])
        started = ws.wait_for(
            lambda m: m.get("type") == "run" and m.get("ros2xeno") and (m.get("run") or {}).get("id") == run["id"],
            seen=True,
        )
        names = [f["name"] for f in started["ros2xeno"]]
        assert "wheel_speed_left" in names and "steer_left" not in names
        codec = Codec("\n".join(f"{f['type']} {f['name']}" for f in started["ros2xeno"]))
        assert "wheel_speed_left" in codec.field_names
        ws.send({"type": "setpoint", "fields": {"wheel_speed_left": 1.5}})
        assert ws.wait_for(lambda m: m.get("type") in ("ack", "error"))["type"] == "ack"
        ws.send({"type": "setpoint", "fields": {"steer_left": 1.5}})
        err = ws.wait_for(lambda m: m.get("type") in ("ack", "error"))
        assert err["type"] == "error" and "steer_left" in err["error"]
    server.stop_run()


def test_templates_new_and_download(server: Server) -> None:
    r = server.http.post("/api/projects/from-template", json={"template": "20sim", "name": "mine"})
    assert r.status_code == 201, r.text
    pid = r.json()["id"]
    z = zipfile.ZipFile(io.BytesIO(server.http.get(f"/api/projects/{pid}/download").content))
    assert "mine/CMakeLists.txt" in z.namelist() and "mine/controller/LoopController_tokens.xml" in z.namelist()
    z = zipfile.ZipFile(io.BytesIO(server.http.get("/api/project-templates/base/download").content))
    assert "my_base/msg/Ros2Xeno.msg" in z.namelist()
    # the downloaded zip uploads again as it is
    r = upload(server.http, server.http.get(f"/api/projects/{pid}/download").content, "mine.zip")
    assert r.status_code == 201, r.text


def test_students_do_not_see_each_other(server: Server) -> None:
    pw_a = server.create_user("proj_alice")
    pw_b = server.create_user("proj_bob")
    alice, alice_ws = server.login("proj_alice", pw_a)
    bob, bob_ws = server.login("proj_bob", pw_b)
    pid = upload(alice, targz(hostile.project_files(BASE))).json()["project"]["id"]
    # build output goes to the owner (and educators), not to other students
    with alice_ws() as wa, bob_ws() as wb, server.ws() as we:
        for w in (wa, wb, we):
            w.send({"type": "subscribe", "topics": ["build"]})
            w.wait_type("ack")
        b = build_and_wait(alice, pid)
        assert b["status"] == "ok"
        for w in (wa, we):
            w.wait_for(lambda m: m.get("build_id") == b["id"] and m.get("status") == "ok", timeout=10, seen=True)
        with pytest.raises(AssertionError):
            wb.wait_for(lambda m: m.get("build_id") == b["id"], timeout=1, seen=True)
    assert [p["id"] for p in alice.get("/api/projects").json()] == [pid]
    assert pid not in [p["id"] for p in bob.get("/api/projects").json()]
    for method, path in (
        ("GET", f"/api/projects/{pid}"),
        ("POST", f"/api/projects/{pid}/builds"),
        ("GET", f"/api/projects/{pid}/download"),
        ("DELETE", f"/api/projects/{pid}"),
        ("GET", f"/api/projects/{pid}/source?path=CMakeLists.txt"),
    ):
        assert bob.request(method, path).status_code == 404, (method, path)
    assert server.http.get(f"/api/projects/{pid}").status_code == 200  # the educator sees it
    alice.close()
    bob.close()


def test_projects_route_starts_a_run_like_the_bench_route(server: Server) -> None:
    """One start-a-run service (server/runs/start.py): a project build started from the Projects
    page gets the timing option and the lease's bookkeeping as POST /api/runs does. Here an
    educator holds the bench and runs a student's build (the run is the student's): the run's
    end must count as the holder's activity (lease.started_run noted the run), so the idle time
    starts again at the end, not at the start. The Projects route skipped that before."""
    server.stop_run()
    pw = server.create_user("proj_carol")
    carol, _ = server.login("proj_carol", pw)
    pid = upload(carol, targz(hostile.project_files(BASE))).json()["project"]["id"]
    b = build_and_wait(carol, pid)
    assert b["status"] == "ok", b["result"]
    carol.close()
    assert server.http.post("/api/lease/take").status_code == 200
    try:
        before = time.monotonic()
        # 1000 Hz: the loop leaves by itself after 3 s, nobody driving meanwhile
        r = server.http.post(
            f"/api/projects/{pid}/builds/{b['id']}/run", json={"max_cycles": 3000, "log_timing": True}, timeout=60
        )
        assert r.status_code == 201, r.text
        run = r.json()["run"]
        assert run["owner"] == "proj_carol"
        deadline = time.monotonic() + 30
        while server.http.get(f"/api/runs/{run['id']}").json()["status"] == "running":
            assert time.monotonic() < deadline, "the run did not end by itself"
            time.sleep(0.1)
        idle_left = server.http.get("/api/lease").json()["idle_left_s"]
        since_start = time.monotonic() - before
        ended = server.http.get(f"/api/runs/{run['id']}").json()
        assert ended["end_reason"] == "cycle_limit", ended
        # the idle time restarted at the run's end (>= 2.5 s after the start request)
        assert idle_left > 600 - since_start + 2.0, (idle_left, since_start)
        # the timing option reached the loop: the run has its cycle_timing log, every cycle of it
        info = server.http.get(f"/api/logs/runs/{run['id']}").json()
        files = {f["name"]: f for f in info["files"]}
        assert "cycle_timing.xrf" in files, files.keys()
        assert files["cycle_timing.xrf"]["records"] == info["run"]["cycles"] == 3000
        audit = server.http.get("/api/audit", params={"username": "admin", "action": "run.start"}).json()
        assert any(e["detail"].get("run") == run["id"] and e["detail"].get("project") == pid for e in audit)
    finally:
        server.http.post("/api/lease/release")


def test_xrf_upload_cli(server: Server, tmp_path: Path) -> None:
    project = tmp_path / "cli_proj"
    env = dict(os.environ, PYTHONPATH=str(REPO / "appliance"))
    r = subprocess.run(
        [sys.executable, "-m", "xrflab.cli", "new", "--template", "base", str(project)],
        capture_output=True,
        text=True,
        env=env,
    )
    assert r.returncode == 0, r.stderr
    (project / "build").mkdir()
    (project / "build" / "junk.o").write_bytes(b"\0" * 1000)
    os.symlink("/etc/passwd", project / "src" / "link")
    import httpx

    pw = server.create_user("proj_cli")
    tok = httpx.post(server.url + "/api/auth/token", json={"username": "proj_cli", "password": pw})
    assert tok.status_code < 300, tok.text
    headers_env = dict(env, XRF_TOKEN=tok.json()["token"])
    r = subprocess.run(
        [sys.executable, "-m", "xrflab.cli", "upload", str(project), "--url", server.url, "--build"],
        capture_output=True,
        text=True,
        env=headers_env,
        timeout=300,
    )
    assert r.returncode == 0, (r.stdout, r.stderr)
    assert "left out src/link" in r.stderr
    assert "build" in r.stdout and ": ok:" in r.stdout
