"""A loop that dies or hangs: outputs safe within 100 ms, run marked crashed, alarm sent,
appliance still serving."""

from __future__ import annotations

import os
import signal
import time
from typing import Any

from xrflab.channels import Channels

from harness import Server, WsClient


def drive_motors(ws: WsClient) -> None:
    """RUN with a setpoint far away, so the wheels are being driven when the loop dies."""
    assert ws.command("initialise")["accepted"]
    ws.wait_state("INITIALISED")
    assert ws.command("start")["accepted"]
    ws.wait_state("RUN")
    ws.send({"type": "setpoint", "fields": {"steer_left": 50.0, "steer_right": 50.0}})
    ws.wait_for(lambda m: m["type"] == "telemetry" and any(m["pwm"]), timeout=5)


def wait_forced_off(ch: Channels, t_event: float, timeout: float = 2.0) -> float:
    """Seconds from t_event until the supervisor forced the simulated outputs off."""
    while not ch.shm.sim.forced_off:
        if time.monotonic() - t_event > timeout:
            raise AssertionError("simulated outputs were not forced off")
        time.sleep(0.0005)
    return time.monotonic() - t_event


def still_serving(server: Server) -> None:
    assert server.http.get("/api/bench").status_code == 200
    run = server.start_run("relbot")  # and can start the next run
    assert run["status"] == "running"
    assert server.stop_run()["status"] == "ended"


def test_kill_9_mid_run(server: Server, running: dict[str, Any]) -> None:
    # Our own view of the run's shared memory, kept mapped across the unlink the supervisor does.
    ch = Channels.open(running["shm"], wait_s=5)
    with server.ws() as ws, server.ws() as watcher:
        drive_motors(ws)
        assert ch.status().state_name == "RUN"
        t_kill = time.monotonic()
        os.kill(running["pid"], signal.SIGKILL)
        safe_after = wait_forced_off(ch, t_kill)
        assert safe_after < 0.100, f"outputs safe only {safe_after * 1000:.1f} ms after the kill"

        for client in (ws, watcher):  # every dashboard hears it
            alarm = client.wait_type("alarm", kind="crash", timeout=5)
            assert alarm["exit_signal"] == signal.SIGKILL
            assert "forced off" in alarm["safe_state"]
        ended = watcher.wait_type("run", event="ended")
        assert ended["active"] is False and ended["run"]["crashed"]
        state = watcher.wait_type("state", seen=True, active=False)
        assert state["allowed"] == []

    row = server.http.get(f"/api/runs/{running['id']}").json()
    assert row["status"] == "crashed" and row["crashed"] and row["crash_reason"] == "signal"
    assert row["exit_signal"] == signal.SIGKILL and row["exit_code"] is None
    assert row["state"] == "RUN" and row["cycles"] > 0
    assert not os.path.exists(f"/dev/shm/{running['shm']}"), "shared memory left behind"
    ch.close()
    still_serving(server)


def test_hang_detected_from_heartbeat(server: Server, running: dict[str, Any]) -> None:
    ch = Channels.open(running["shm"], wait_s=5)
    with server.ws() as ws:
        drive_motors(ws)
        t_stop = time.monotonic()
        os.kill(running["pid"], signal.SIGSTOP)  # alive, but no more cycles
        detected = wait_forced_off(ch, t_stop, timeout=3)
        # hang_timeout_ms is 200 ms by default; the check runs every 50 ms
        assert 0.15 < detected < 0.6, f"hang handled after {detected * 1000:.0f} ms"
        alarm = ws.wait_type("alarm", kind="hang", timeout=5)
        assert "hung" in alarm["message"]
    row = server.http.get(f"/api/runs/{running['id']}").json()
    assert row["status"] == "crashed" and row["crash_reason"] == "hang"
    assert row["exit_signal"] == signal.SIGKILL
    ch.close()
    still_serving(server)


def test_loop_exit_on_its_own_is_not_a_crash(server: Server) -> None:
    server.stop_run()
    run = server.start_run("relbot", max_cycles=1500)
    with server.ws() as ws:
        ended = ws.wait_type("run", event="ended", timeout=10)
    assert not ended["run"]["crashed"] and ended["run"]["exit_code"] == 0
    assert server.http.get(f"/api/runs/{run['id']}").json()["status"] == "ended"


def test_appliance_death_pauses_the_loop_and_restart_cleans_up(tmp_path) -> None:
    from harness import shared_builds_root, start_server, stop_server

    s = start_server(tmp_path, shared_builds_root())
    restarted = None
    try:
        run = s.start_run("relbot")
        ch = Channels.open(run["shm"], wait_s=5)
        with s.ws() as ws:
            drive_motors(ws)
        os.kill(s.proc.pid, signal.SIGKILL)  # the appliance dies; the loop must not care...
        s.proc.wait()
        t0 = time.monotonic()
        while ch.status().state_name != "PAUSED":  # ...except that it pauses itself (1 s timeout)
            assert time.monotonic() - t0 < 3, ch.status().state_name
            time.sleep(0.01)
        assert ch.status().running and ch.status().host_lost >= 1
        # A new appliance on the same data folder stops the orphan and records what happened.
        restarted = start_server(tmp_path, shared_builds_root())
        deadline = time.monotonic() + 10
        while _alive(run["pid"]) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert not _alive(run["pid"]), "orphaned loop still running"
        assert not os.path.exists(f"/dev/shm/{run['shm']}")
        row = restarted.http.get(f"/api/runs/{run['id']}").json()
        assert row["crashed"] and row["crash_reason"] == "appliance"
        ch.close()
    finally:
        if _alive(run["pid"]):
            os.kill(run["pid"], signal.SIGKILL)
        for server in (restarted, s):
            if server is not None and server.proc.poll() is None:
                stop_server(server)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False
