"""The 3D view in a real appliance: viser starts with it on its own port and serves its client
from the wheel (no CDN), the Jiwy joints follow the encoders after a setpoint change, the
setpoint shows as a ghost, RELbot odometry moves and resets, a finished run replays."""

from __future__ import annotations

import re
import time
import urllib.parse
from typing import Any, Callable

import httpx

from harness import Server


def wait_state(server: Server, pred: Callable[[dict[str, Any]], bool], timeout: float = 10.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while True:
        s = server.http.get("/api/viz/state").json()
        if pred(s):
            return s
        if time.monotonic() > deadline:
            raise AssertionError(f"3D view state never matched; last {s}")
        time.sleep(0.05)


def to_run(server: Server, build: str) -> None:
    server.stop_run()
    server.start_run(build)
    with server.ws() as ws:
        ws.wait_state("IDLE", 20)
        assert ws.command("initialise")["accepted"]
        ws.wait_state("INITIALISED")
        assert ws.command("start")["accepted"]
        ws.wait_state("RUN")


def test_viser_serves_its_client_offline(server: Server) -> None:
    info = server.http.get("/api/viz").json()
    assert info["available"], info
    app_port = urllib.parse.urlsplit(server.url).port
    assert info["port"] and info["port"] != app_port
    r = httpx.get(f"http://127.0.0.1:{info['port']}/", timeout=10)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    html = r.text
    # The client is one self-contained page (the app is inlined, compressed): every tag that loads
    # something must point at this server or be inline data.
    refs = re.findall(r"<(?:script|link|img|iframe)\b[^>]*?\b(?:src|href)\s*=\s*[\"']([^\"']+)", html, re.I)
    assert all(ref.startswith(("data:", "/", "./")) or "://" not in ref for ref in refs), refs
    head = re.sub(r'data-p="[^"]*"', "", html)  # the compressed bundle is not readable text
    head = re.sub(r'<script[^>]*>.*?</script>', "", head, flags=re.S)
    head = re.sub(r'"data:[^"]*"', '""', head)  # inline data (the icon's SVG names its xmlns)
    assert not re.search(r"https?://", head), re.findall(r"https?://[^\s\"'<>]+", head)


def test_jiwy_joints_follow_the_setpoint_and_replay(server: Server) -> None:
    to_run(server, "jiwy")
    s = wait_state(server, lambda s: s.get("kind") == "pan_tilt" and s.get("mode") == "live")
    assert abs(s["joints"]["pan"]) < 0.05 and s["message"] == ""
    with server.ws() as ws:
        ws.send({"type": "setpoint", "fields": {"pan_setpoint": 0.6, "tilt_setpoint": -0.3}})
        s = wait_state(server, lambda s: abs(s["joints"]["pan"] - 0.6) < 0.03 and abs(s["joints"]["tilt"] + 0.3) < 0.03)
        assert s["ghost"] == {"pan": 0.6, "tilt": -0.3}
        # The example's own measurement (Xeno2Ros pan/tilt, from the same counters) agrees.
        t = ws.wait_for(lambda m: m.get("type") == "telemetry" and abs(m["xeno2ros"]["pan"] - 0.6) < 0.03, 5)
        assert abs(t["xeno2ros"]["tilt"] - s["joints"]["tilt"]) < 0.03
    run_id = s["run_id"]
    server.stop_run()
    recs = server.http.get("/api/viz/recordings").json()
    assert any(r["run_id"] == run_id and not r["active"] for r in recs), recs
    r = server.http.post("/api/viz/replay", json={"run_id": run_id})
    assert r.status_code == 200, r.text
    duration = r.json()["duration"]
    assert r.json()["kind"] == "pan_tilt" and duration > 0.5
    server.http.post("/api/viz/replay/seek", json={"t": 0.0})
    s = wait_state(server, lambda s: s["mode"] == "replay" and s["t"] == 0.0)
    assert abs(s["joints"]["pan"]) < 0.05 and s["ghost"] is None
    server.http.post("/api/viz/replay/seek", json={"t": duration})
    s = wait_state(server, lambda s: s["mode"] == "replay" and s["t"] == duration)
    assert abs(s["joints"]["pan"] - 0.6) < 0.03 and s["ghost"] == {"pan": 0.6, "tilt": -0.3}
    assert server.http.post("/api/viz/live").status_code == 200


def test_relbot_odometry_moves_and_resets(server: Server) -> None:
    to_run(server, "relbot")
    wait_state(server, lambda s: s.get("kind") == "differential_drive" and s.get("mode") == "live")
    with server.ws() as ws:
        # both wheels 3 rad forward: 3 * 0.0505 = 0.1515 m straight ahead (the setpoint is sent
        # again while waiting: one sent in the loop's first cycles of RUN can be missed)
        deadline = time.monotonic() + 20
        while True:
            ws.send({"type": "setpoint", "fields": {"steer_left": 3.0, "steer_right": 3.0}})
            s = server.http.get("/api/viz/state").json()
            if abs(s["pose"]["x"] - 0.1515) < 0.01 or time.monotonic() > deadline:
                break
            time.sleep(0.5)
    assert abs(s["pose"]["x"] - 0.1515) < 0.01, s
    assert abs(s["pose"]["y"]) < 0.01 and abs(s["pose"]["theta"]) < 0.03
    assert server.http.post("/api/viz/reset-odometry").status_code == 200
    s = wait_state(server, lambda s: abs(s["pose"]["x"]) < 1e-9)
    assert s["pose"] == {"x": 0.0, "y": 0.0, "theta": 0.0}
    server.stop_run()
