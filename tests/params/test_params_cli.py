"""`xrf param` on a 20-sim-style export with `PID_Left\\Kp`-style names (issue 28).

The fixture (tests/fixtures/twentysim_pid) is a tokens file in 20-sim's layout naming two PIDs'
six parameters; it replaces the 20-sim template's own, and the project is uploaded, built and run
through the appliance like a student's. The real `xrf` command, as a subprocess with an API
token, lists them, refuses a bad set whole and applies a good one at a confirmed cycle.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from xrf_testing import hostile
from xrf_testing.harness import ADMIN_PASSWORD, ADMIN_USER, Server, shared_builds_root, start_server, stop_server
from xrf_testing.projects_support import reachable_tmp, targz, upload_and_build

REPO = Path(__file__).resolve().parents[2]
TWENTY = REPO / "student_projects/templates/20sim"
FIXTURE = REPO / "tests/fixtures/twentysim_pid/LoopController_tokens.xml"
NAMES = ["PID_Left\\Kp", "PID_Left\\Ki", "PID_Left\\Kd", "PID_Right\\Kp", "PID_Right\\Ki", "PID_Right\\Kd"]


@pytest.fixture(scope="module")
def server() -> Iterator[Server]:
    data = reachable_tmp("data")  # the build user must reach the projects folder
    s = start_server(data, shared_builds_root())
    yield s
    stop_server(s)
    shutil.rmtree(data, ignore_errors=True)


def xrf(server: Server, token: str, *args: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=str(REPO / "appliance"), XRF_URL=server.url, XRF_TOKEN=token, HOME="/nonexistent")
    return subprocess.run(
        [sys.executable, "-m", "xrflab.cli", "param", *args], env=env, capture_output=True, text=True, timeout=60
    )


def test_parameters_table_from_the_fixture() -> None:
    from xrflab.twentysim_params import parameters, parse_tokens

    params, problems = parameters(parse_tokens(FIXTURE.read_text()))
    assert problems == []
    assert [p.name for p in params] == NAMES
    assert [p.default for p in params] == [1.0, 0.0, 0.05, 1.0, 0.0, 0.05]
    assert params[1].unit == "-/(rad.s)"


def test_xrf_param_on_a_20sim_export(server: Server) -> None:
    files = hostile.project_files(TWENTY)
    files["controller/LoopController_tokens.xml"] = FIXTURE.read_bytes()
    pid, bid = upload_and_build(server.http, targz(files, "two_wheel_pid"), "two_wheel_pid.tar.gz")
    info = server.http.get(f"/api/projects/{pid}").json()["twenty_sim"]
    assert [p["name"] for p in info["parameters"]] == NAMES
    token = server.http.post("/api/auth/token", json={"username": ADMIN_USER, "password": ADMIN_PASSWORD}).json()[
        "token"
    ]
    server.stop_run()
    with server.ws() as ws:
        ws.send({"type": "subscribe", "topics": ["state"]})
        r = server.http.post(f"/api/projects/{pid}/builds/{bid}/run", json={}, timeout=60)
        assert r.status_code == 201, r.text
        ws.wait_state("IDLE", timeout=20)
        assert ws.command("initialise")["accepted"]
        ws.wait_state("INITIALISED", 10)
        assert ws.command("start")["accepted"]
        ws.wait_state("RUN", 10)

        out = xrf(server, token, "list")
        assert out.returncode == 0, out.stderr
        rows = out.stdout.splitlines()
        assert [row.split()[0] for row in rows] == NAMES
        assert "-/(rad.s)" in rows[1]

        bad = xrf(server, token, "set", "PID_Left\\Kp=2.5", "PID_Right\\Kx=1")
        assert bad.returncode == 1 and "unknown parameter 'PID_Right\\Kx'" in bad.stderr
        bad = xrf(server, token, "set", "PID_Left\\Kp=fast")
        assert bad.returncode == 1 and "not a number" in bad.stderr
        got = json.loads(xrf(server, token, "--json", "get", "PID_Left\\Kp").stdout)
        assert got["value"] == 1.0  # nothing of the refused sets landed

        ok = xrf(server, token, "set", "PID_Left\\Kp=2.5", "PID_Right\\Kd=0.1")
        assert ok.returncode == 0, ok.stderr
        assert "PID_Left\\Kp: 1 -> 2.5" in ok.stdout and "applied at cycle " in ok.stdout
        cycle = int(ok.stdout.rsplit("applied at cycle ", 1)[1])
        assert cycle > 0
        listing = json.loads(xrf(server, token, "--json", "list").stdout)
        values = {p["name"]: p["value"] for p in listing["params"]}
        assert values["PID_Left\\Kp"] == 2.5 and values["PID_Right\\Kd"] == 0.1 and values["PID_Left\\Ki"] == 0.0

        # Keep what worked: every gain 0 (the PIDs then steer nothing), saved as the project's
        # next version (the panel's button does these two requests), and the next run of the
        # same build starts with it, through 20-sim's Initialize() which writes the defaults.
        zero = [f"{n}=0" for n in NAMES]
        assert xrf(server, token, "set", *zero).returncode == 0
        f = server.http.get("/api/params-file").json()
        assert f["path"] == "xrf_params.json" and json.loads(f["content"])["parameters"]["PID_Left\\Kp"] == 0.0
        r = server.http.put(f"/api/projects/{pid}/files/{f['path']}", params={"build": "false"}, content=f["content"])
        assert r.status_code == 200 and r.json()["new_version"], r.text
        shown = server.http.get(f"/api/projects/{pid}/files/xrf_params.json").json()  # in the editor
        assert shown["content"] == f["content"] and shown["version"] == r.json()["version"]["n"]
        server.stop_run()

        ws.messages.clear()
        ws.send({"type": "subscribe", "topics": ["state", "telemetry", "params"]})
        ws.wait_type("ack")
        r = server.http.post(f"/api/projects/{pid}/builds/{bid}/run", json={}, timeout=60)
        assert r.status_code == 201, r.text
        run2 = r.json()["run"]
        saved = ws.wait_for(lambda m: m.get("type") == "params" and m.get("who") == "saved parameters", 10)
        assert saved["run_id"] == run2["id"] and {c["name"] for c in saved["changes"]} == set(NAMES)
        ws.wait_state("IDLE", timeout=20)
        assert ws.command("initialise")["accepted"]
        ws.wait_state("INITIALISED", 10)
        assert ws.command("start")["accepted"]
        ws.wait_state("RUN", 10)
        ws.send({"type": "setpoint", "fields": {"steer_left": 5.0, "steer_right": 5.0}})
        after = [ws.wait_sample(lambda m: m["state"] == 4, 10) for _ in range(30)]
        assert all(m["pwm"][0] == 0 and m["pwm"][1] == 0 for m in after), [m["pwm"] for m in after]
        assert server.http.get("/api/params/PID_Left\\Kp").json()["value"] == 0.0
    server.stop_run()
