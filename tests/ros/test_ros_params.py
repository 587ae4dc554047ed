"""The controller's tunable parameters as ROS 2 parameters of the appliance's bridge node
(issue 28): `ros2 param list/describe/set` (their services, from a separate rclpy process) on the
20-sim template's PID, names with `\\` mapped to `.`, a set applied through the appliance (the
bench holder's only, checked whole, in the run's change table), a bad one refused.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from xrf_testing.harness import Server

pytestmark = pytest.mark.ros

PEER = Path(__file__).with_name("ros_param_peer.py")
NODE = "ros_xeno_bridge"


def params_peer(ros_domain: dict[str, str], *args: str, server: Server | None = None) -> dict[str, Any]:
    env = dict(os.environ, **ros_domain)
    r = subprocess.run([sys.executable, str(PEER), NODE, *args], env=env, capture_output=True, text=True, timeout=90)
    bridge = server.http.get("/api/ros").json() if server else None
    assert r.returncode == 0, (r.stdout + r.stderr, bridge)
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_ros2_param_set_on_the_bridge(server: Server, ros_domain: dict[str, str]) -> None:
    http = server.http
    assert http.post("/api/lease/take").status_code == 200
    server.stop_run()
    run = server.start_run("template-20sim")
    assert http.post("/api/ros", json={"enabled": True}).status_code == 200
    deadline = time.monotonic() + 20
    while http.get("/api/ros").json()["state"] != "running":
        assert time.monotonic() < deadline, http.get("/api/ros").json()
        time.sleep(0.1)
    try:
        got = params_peer(ros_domain)
        # rclpy's own (use_sim_time, start_type_description_service) aside
        assert [n for n in got["list"] if n.startswith("PID")] == sorted(
            ["PID1.Kp", "PID1.Ki", "PID1.Kd", "PID2.Kp", "PID2.Ki", "PID2.Kd", "PID.tau_d", "PID.limit"]
        )
        assert got["describe"]["PID1.Kp"]["description"] == "PID1\\Kp [-/rad] (default 1)"
        assert got["get"]["PID1.Kp"] == 1.0

        got = params_peer(ros_domain, "PID1.Kp=2.5", "PID2.Kd=0.2", "--atomic", server=server)
        assert got["set"][0]["successful"], got
        assert got["get"]["PID1.Kp"] == 2.5
        values = {p["name"]: p["value"] for p in http.get("/api/params").json()["params"]}
        assert values["PID1\\Kp"] == 2.5 and values["PID2\\Kd"] == 0.2

        got = params_peer(ros_domain, "PID1.Kp=1e9", "--atomic", server=server)  # outside the proposed range
        assert not got["set"][0]["successful"] and "out of range" in got["set"][0]["reason"], got
        assert http.get("/api/params/PID1\\Kp").json()["value"] == 2.5  # nothing applied

        changes = http.get(f"/api/logs/runs/{run['id']}/param-changes").json()["changes"]
        assert all(c["cycle"] > 0 for c in changes)  # the loop's confirmed cycle
        assert {(c["name"], c["new"], c["who"]) for c in changes} == {
            ("PID1\\Kp", 2.5, "admin (ROS 2)"),
            ("PID2\\Kd", 0.2, "admin (ROS 2)"),
        }

        # A set from the dashboard (or `xrf param`, the same route): `ros2 param get` follows,
        # and the bridge does not send it back as a set of its own (no "(ROS 2)" change).
        r = http.post("/api/params", json={"values": {"PID1\\Kp": 0.75, "PID\\limit": 0.5}})
        assert r.status_code == 200, r.text
        deadline = time.monotonic() + 20
        while (got := params_peer(ros_domain, server=server)["get"])["PID1.Kp"] != 0.75:
            assert time.monotonic() < deadline, got
        assert got["PID.limit"] == 0.5 and got["PID2.Kd"] == 0.2
        changes = http.get(f"/api/logs/runs/{run['id']}/param-changes").json()["changes"]
        assert [c["who"] for c in changes].count("admin (ROS 2)") == 2 and len(changes) == 4, changes
        # Not the holder: refused (the lease released, the bridge's user holds nothing).
        assert http.post("/api/lease/release").status_code == 200
        got = params_peer(ros_domain, "PID1.Kp=3", "--atomic", server=server)
        assert not got["set"][0]["successful"] and "lease" in got["set"][0]["reason"], got
    finally:
        http.post("/api/ros", json={"enabled": False})
        server.stop_run()
