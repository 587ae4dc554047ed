"""REST API against a real appliance and real relbot loop processes."""

from __future__ import annotations

from xrf_testing.harness import Server


def test_bench_is_simulated(server: Server) -> None:
    bench = server.http.get("/api/bench").json()
    assert bench["mode"] == "sim"
    assert bench["sim"] == "relbot"
    assert bench["telemetry_hz"] == 30  # samples a second
    assert bench["telemetry_per_message"] == 6  # in 5 messages a second


def test_builds_list_bundled_examples_and_templates(server: Server) -> None:
    builds = {b["name"]: b for b in server.http.get("/api/builds").json()}
    assert {"relbot", "jiwy"} <= set(builds)
    assert builds["relbot"]["kind"] == "example" and builds["relbot"]["sim"] == "relbot"
    assert builds["jiwy"]["sim"] == "jiwy"
    assert any(b["kind"] == "template" for b in builds.values())


def test_openapi_is_the_contract(server: Server) -> None:
    schema = server.http.get("/openapi.json").json()
    for path in ("/api/bench", "/api/builds", "/api/runs", "/api/runs/current/stop", "/api/runs/{run_id}"):
        assert path in schema["paths"], path
    assert {"RunRecord", "StartRun", "BuildInfo", "BenchInfo"} <= set(schema["components"]["schemas"])


def test_dashboard_is_served(server: Server) -> None:
    page = server.http.get("/")
    assert page.status_code == 200 and "XRF Lab" in page.text
    assert server.http.get("/static/app.js").status_code == 200
    assert server.http.get("/static/vendor/uplot/uPlot.iife.min.js").status_code == 200


def test_run_lifecycle(server: Server) -> None:
    server.stop_run()
    run = server.start_run("relbot")
    assert run["status"] == "running" and run["pid"] > 0 and run["cycle_freq"] > 0
    # One run at a time.
    again = server.http.post("/api/runs", json={"build": "relbot"})
    assert again.status_code == 409

    for cmd, _state in (("initialise", "INITIALISED"), ("start", "RUN")):
        r = server.http.post("/api/runs/current/command", json={"cmd": cmd})
        assert r.status_code == 200 and r.json()["accepted"], r.text
    # Wait for INITIALISING -> INITIALISED happened before start was accepted: start is only
    # allowed from INITIALISED, so its acceptance proves it.
    rejected = server.http.post("/api/runs/current/command", json={"cmd": "quit"}).json()
    assert not rejected["accepted"] and "not allowed" in rejected["reason"]
    assert server.http.post("/api/runs/current/command", json={"cmd": "fly"}).status_code == 422

    ended = server.stop_run()
    assert ended is not None
    assert ended["status"] == "ended" and not ended["crashed"]
    assert ended["exit_code"] == 0 and ended["state"] == "QUIT"
    assert ended["cycles"] > 0
    listed = server.http.get("/api/runs").json()
    assert listed[0]["id"] == run["id"]
    assert server.http.get(f"/api/runs/{run['id']}").json()["status"] == "ended"


def test_stop_from_idle_uses_sigint(server: Server) -> None:
    server.stop_run()
    server.start_run("relbot")
    ended = server.stop_run()  # IDLE: quit is not allowed, so the supervisor sends SIGINT
    assert ended is not None and not ended["crashed"]


def test_errors(server: Server) -> None:
    server.stop_run()
    assert server.http.post("/api/runs", json={"build": "nope"}).status_code == 404
    assert server.http.post("/api/runs", json={}).status_code == 422
    assert server.http.get("/api/runs/999999").status_code == 404
    assert server.http.post("/api/runs/current/stop").status_code == 409
    assert server.http.post("/api/runs/current/command", json={"cmd": "start"}).status_code == 409
