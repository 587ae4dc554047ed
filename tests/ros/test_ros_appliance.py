"""The ROS 2 bridge run by the appliance (docs/ros2/bridge.md, "Run by the appliance").

Real appliance (harness subprocess), real relbot loop, the real bridge spawned by the appliance,
and a separate rclpy node process talking DDS on loopback: the dashboard toggle starts the
bridge for the active run; ROS 2 commands obey the bench lease of the bridge's user (the STOP
rule lets stop/pause through); a killed bridge is restarted; switching it off ends the process.
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from xrf_testing.harness import Server

pytestmark = pytest.mark.ros

STATE = {"INITIALISED": 3, "RUN": 4, "STOPPED": 6, "PAUSED": 8}


def ros(server: Server) -> dict[str, Any]:
    r = server.http.get("/api/ros")
    assert r.status_code == 200, r.text
    return r.json()


def wait_ros(server: Server, pred: Callable[[dict[str, Any]], bool], timeout: float, what: str) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while True:
        st = ros(server)
        if pred(st):
            return st
        if time.monotonic() > deadline:
            raise AssertionError(f"ROS bridge: no {what} within {timeout} s: {st}")
        time.sleep(0.1)


def gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return Path(f"/proc/{pid}/stat").read_text().split()[2] == "Z"


def test_bridge_run_by_the_appliance_obeys_the_lease(server: Server, peer) -> None:
    http = server.http  # the harness's educator, "admin"
    assert ros(server)["state"] == "stopped" and ros(server)["enabled"] is False
    assert http.post("/api/lease/take").status_code == 200
    run = server.start_run("relbot")
    # Toggle on while the run is active: the appliance spawns the bridge for this run.
    r = http.post("/api/ros", json={"enabled": True})
    assert r.status_code == 200, r.text
    st = wait_ros(server, lambda s: s["state"] == "running" and s["pid"], 10, "running bridge")
    assert st["run_id"] == run["id"] and st["user"] == "admin"
    assert st["topics"] == ["XenoCmd", "XenoState", "Ros2Xeno", "Xeno2Ros"]
    pid = st["pid"]
    output = Path(run["run_dir"]) / "ros-bridge.txt"

    # 1 then 2 from ROS 2 with the educator holding the lease: RUN.
    assert peer.ask("ready 40", 40)["ok"], output.read_text()
    peer.ask("cmd 1", 5)
    assert peer.ask("wait 3 10", 10)["ok"], output.read_text()
    peer.ask("cmd 2", 5)
    assert peer.ask("wait 4 10", 10)["ok"], output.read_text()

    # The lease goes to a student: the bridge (acting for admin) may only stop and pause now.
    pw = server.create_user("rosstudent", "student")
    student, _ = server.login("rosstudent", pw)
    assert http.post("/api/lease/release").status_code == 200
    assert student.post("/api/lease/take").status_code == 200
    peer.ask("cmd 5", 5)  # pause: the STOP rule
    assert peer.ask("wait 8 10", 10)["ok"], output.read_text()
    peer.ask("cmd 2", 5)  # start (the loop would accept it in PAUSED): refused by the gate
    held = peer.ask("hold 1.5", 5)
    assert held["state"] == STATE["PAUSED"] and STATE["RUN"] not in held["states"], held
    text = output.read_text()
    assert "XenoCmd 2 (start) refused for user 'admin'" in text and "rosstudent holds it" in text, text
    peer.ask("cmd 3", 5)  # stop: the STOP rule
    assert peer.ask("wait 6 10", 10)["ok"], output.read_text()
    audit = http.get("/api/audit", params={"action": "command"}).json()
    ros_rows = [a["detail"] for a in audit if a["detail"].get("via") == "ros"]
    assert {(d["cmd"], d["allowed"]) for d in ros_rows} >= {("start", True), ("start", False), ("stop", True)}
    # A student may not switch the bridge; everybody may see it.
    assert student.post("/api/ros", json={"enabled": False}).status_code == 403
    assert student.get("/api/ros").json()["pid"] == pid

    # Bridge killed: restarted for the same run.
    os.kill(pid, signal.SIGKILL)
    st = wait_ros(server, lambda s: s["state"] == "running" and s["pid"] not in (None, pid), 15, "restarted bridge")
    assert st["restarts"] >= 1 and st["run_id"] == run["id"]
    new_pid = st["pid"]

    # Toggle off: the bridge process is gone.
    r = http.post("/api/ros", json={"enabled": False})
    assert r.status_code == 200 and r.json()["state"] == "stopped" and r.json()["pid"] is None, r.text
    assert gone(new_pid)
    toggles = [a["detail"]["enabled"] for a in http.get("/api/audit", params={"action": "ros"}).json()]
    assert toggles[:2] == [False, True]  # newest first
    student.close()
    server.stop_run()


def test_bridge_follows_the_run(server: Server) -> None:
    """Enabled before the run: started with it, stopped (process gone) when the run ends."""
    http = server.http
    server.stop_run()  # nothing left from another test
    assert http.post("/api/ros", json={"enabled": True}).status_code == 200
    assert ros(server)["state"] == "stopped"  # no run, no bridge
    run = server.start_run("relbot")
    st = wait_ros(server, lambda s: s["state"] == "running" and s["run_id"] == run["id"], 10, "bridge of the new run")
    pid = st["pid"]
    server.stop_run()
    st = wait_ros(server, lambda s: s["state"] == "stopped", 15, "bridge stopped with the run")
    assert st["pid"] is None and gone(pid), st
    assert "xrf ros-bridge for user 'admin'" in (Path(run["run_dir"]) / "ros-bridge.txt").read_text()
    assert http.post("/api/ros", json={"enabled": False}).status_code == 200
