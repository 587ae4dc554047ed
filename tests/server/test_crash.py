"""A loop that dies or hangs: outputs safe within 100 ms, run marked crashed, alarm sent,
appliance still serving."""

from __future__ import annotations

import contextlib
import os
import signal
import time
from typing import Any

from xrf_testing.grpcweb import watch_live
from xrf_testing.harness import Server, WsClient, wait_for
from xrf_testing.leaks import descendants
from xrflab.channels import Channels, lib


def _brake_only(channel: int) -> list[int]:
    """Every channel any bench can have off, but the brake's (1-based)."""
    return [int(i == channel - 1) for i in range(lib.XRF_MAX_CHANNELS)]


def drive_motors(ws: WsClient) -> None:
    """RUN with a setpoint far away, so the wheels are being driven when the loop dies."""
    assert ws.command("initialise")["accepted"]
    ws.wait_state("INITIALISED")
    assert ws.command("start")["accepted"]
    ws.wait_state("RUN")
    ws.send({"type": "setpoint", "fields": {"steer_left": 50.0, "steer_right": 50.0}})
    ws.wait_sample(lambda s: any(s["pwm"]), timeout=5)


def wait_forced_off(ch: Channels, t_event: float, timeout: float = 2.0) -> float:
    """Seconds from t_event until the supervisor forced the simulated outputs off."""
    while not ch.shm.sim.forced_off:
        if time.monotonic() - t_event > timeout:
            raise AssertionError("simulated outputs were not forced off")
        time.sleep(0.0005)  # a latency is measured: poll finer than wait_for's 50 ms
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


def test_crashed_runs_leave_nothing_open_in_the_appliance(server: Server) -> None:
    """A run's mapping (10 MB) and descriptors go when it ends, not when the garbage collector
    gets round to it: a day of crashes must not pile them up in the appliance."""

    def fds() -> list[str]:
        out = []
        for name in os.listdir(f"/proc/{server.proc.pid}/fd"):
            try:
                out.append(os.readlink(f"/proc/{server.proc.pid}/fd/{name}"))
            except OSError:
                pass
        return out

    server.stop_run()
    run = server.start_run("relbot")
    with server.ws() as ws:
        drive_motors(ws)
    time.sleep(1)  # quiet before counting: the first run's start-up descriptors are closed by now
    before = fds()
    for _ in range(4):
        with server.ws() as ws:
            os.kill(run["pid"], signal.SIGKILL)
            ws.wait_type("alarm", kind="crash", timeout=10)
            ws.wait_type("run", event="ended", timeout=10)
        run = server.start_run("relbot")
        with server.ws() as ws:
            drive_motors(ws)
    # The last run's readers wind down after the WebSocket closes: wait until the descriptors are
    # back (not a fixed second), then say what is left if they never are.
    with contextlib.suppress(AssertionError):
        wait_for(lambda: len(fds()) <= len(before) and not _stale_maps(fds()), 10, "descriptors to close")
    after = fds()
    stale = _stale_maps(after)
    assert not stale, f"mappings of ended runs still open: {stale}"
    assert len(after) <= len(before), sorted(set(after) - set(before))
    server.stop_run()


def _stale_maps(fds: list[str]) -> list[str]:
    """Mappings of shared segments that were removed: an ended run's, still open."""
    return [f for f in fds if f.endswith("(deleted)") and "/dev/shm/" in f]


def test_loop_exit_on_its_own_is_not_a_crash(server: Server) -> None:
    server.stop_run()
    run = server.start_run("relbot", max_cycles=1500)
    with server.ws() as ws:
        ended = ws.wait_type("run", event="ended", timeout=10)
    assert not ended["run"]["crashed"] and ended["run"]["exit_code"] == 0
    row = server.http.get(f"/api/runs/{run['id']}").json()
    assert row["status"] == "ended" and row["end_reason"] == "cycle_limit"


def test_a_stopped_appliance_pauses_the_loop_and_then_says_why(server: Server, running: dict[str, Any]) -> None:
    """The whole appliance stopped (SIGSTOP: its event loop and its watcher thread) for longer
    than host_timeout_ms: the loop pauses itself, and once the appliance runs again every
    dashboard is told why the run is PAUSED (the `host_lost` alarm), not left to guess."""
    with server.ws() as ws:
        assert ws.command("initialise")["accepted"]
        ws.wait_state("INITIALISED")
        assert ws.command("start")["accepted"]
        ws.wait_state("RUN")
        os.kill(server.proc.pid, signal.SIGSTOP)
        try:
            time.sleep(1.6)  # time passing: longer than host_timeout_ms (1 s) without a heartbeat
        finally:
            os.kill(server.proc.pid, signal.SIGCONT)
        alarm = ws.wait_type("alarm", kind="host_lost", timeout=10)
        assert alarm["run_id"] == running["id"] and "went to PAUSED by itself" in alarm["message"], alarm
        assert "did not answer" in alarm["message"]
    ch = Channels.open(running["shm"], wait_s=5)
    try:
        assert ch.status().state_name == "PAUSED" and ch.status().host_lost == 1
    finally:
        ch.close()


def test_appliance_death_pauses_the_loop_and_restart_closes_the_run(tmp_path) -> None:
    """kill -9 of the appliance mid-run: the loop pauses itself (host_timeout_action) and keeps
    cycling; nothing else the appliance started runs on; a restart on the same port and data
    stops the loop, closes the run with the counts from the loop's memory and log (the records
    the dead appliance had not written yet included), frees the bench, and says what happened."""

    from xrf_testing.harness import stop_server
    from xrf_testing.logs_support import PROBE, start

    s = start(tmp_path)
    restarted = None
    run: dict[str, Any] = {}
    try:
        run = s.start_run(PROBE)
        ch = Channels.open(run["shm"], wait_s=5)
        with s.ws() as ws:
            assert ws.command("initialise")["accepted"]
            ws.wait_state("INITIALISED")
            assert ws.command("start")["accepted"]
            ws.wait_state("RUN")
            assert s.http.post("/api/lease/take").status_code == 200  # a holder, to be freed
            ws.wait_sample(lambda s: s["cycle"] > 300, timeout=10)
        assert watch_live(s.http).status == 200  # its live rerun proxy: started at a first viewer
        launcher = _parent_of(_parent_of(run["pid"]))  # controller <- the sandbox's init <- launcher
        children = descendants(s.proc.pid)
        # The loop's own processes (launcher, the sandbox's init, the controller) must live on.
        loop_side = {launcher} | descendants(launcher)
        assert run["pid"] in loop_side and children - loop_side, children  # rerun, viser, ... too
        os.kill(s.proc.pid, signal.SIGKILL)
        s.proc.wait()
        # host_timeout_ms = 1 s, then PAUSE
        wait_for(lambda: ch.status().state_name == "PAUSED", 5, "the loop to pause without its host")
        assert ch.status().running and ch.status().host_lost >= 1
        c0 = ch.status().cycles
        time.sleep(0.3)  # the point: paused, the loop goes on cycling (>100 cycles in 0.3 s)
        assert ch.status().cycles > c0 + 100, "the paused loop stopped cycling"
        with contextlib.suppress(AssertionError):
            wait_for(lambda: not any(_alive(p) for p in children - loop_side), 5, "the appliance's children")
        left = {p for p in children - loop_side if _alive(p)}
        assert not left, f"children of the dead appliance still running: {_cmdlines(left)}"
        cycles_before = ch.status().cycles

        # A new appliance on the same data folder and port.
        restarted = start(tmp_path, port=int(s.url.rsplit(":", 1)[1]))
        wait_for(lambda: not any(_alive(p) for p in loop_side), 15, "the orphaned loop to be stopped")
        assert not os.path.exists(f"/dev/shm/{run['shm']}")
        row = wait_for(
            lambda: (
                (r := restarted.http.get(f"/api/runs/{run['id']}").json())["end_reason"] == "appliance_restart" and r
            ),
            10,
            "the run closed as ended by the restart",
        )
        assert row["crashed"] and row["crash_reason"] == "appliance" and row["status"] == "crashed"
        assert row["cycles"] >= cycles_before and row["state"] in ("PAUSED", "STOPPED", "QUIT"), row
        assert "paused" in row["message"] or "pause" in row["message"], row["message"]
        assert "stopped it" in row["message"], row["message"]
        logs = restarted.http.get(f"/api/logs/runs/{run['id']}").json()
        assert logs["run"]["log_records"] > 0
        in_files = sum(f["records"] for f in logs["files"] if f["kind"] == "xrflog")
        assert logs["run"]["log_records"] == in_files, logs
        # Every record the loop logged is in the files or counted lost: nothing vanished, and
        # nothing twice (the dead appliance may have written records it had not yet released).
        assert logs["run"]["log_records"] + logs["run"]["log_lost"] == ch.status().log_written
        from xrflab.logs.reader import open_log

        for f in logs["files"]:
            if f["kind"] == "xrflog":
                seq = open_log(os.path.join(row["run_dir"], f["name"])).records["seq"]
                assert (seq[1:] > seq[:-1]).all(), f"records repeated or out of order in {f['name']}"
        assert restarted.http.get("/api/lease").json()["holder"] is None
        ch.close()
    finally:
        for p in [run["pid"]] if run.get("pid") else []:
            if _alive(p):
                os.kill(p, signal.SIGKILL)
        for server in (restarted, s):
            if server is not None and server.proc.poll() is None:
                stop_server(server)


def _parent_of(pid: int) -> int:
    with open(f"/proc/{pid}/stat") as f:
        return int(f.read().rsplit(")", 1)[1].split()[1])


def _cmdlines(pids: set[int]) -> list[str]:
    out = []
    for p in pids:
        try:
            with open(f"/proc/{p}/cmdline", "rb") as f:
                text = f.read().replace(b"\0", b" ")[:120].decode(errors="replace")
            out.append(f"{p}: {text}")
        except OSError:
            pass
    return out


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_a_brake_profile_leaves_the_brake_on_when_the_loop_dies(server: Server) -> None:
    """The bench profile's safe reaction reaches the watcher of a real run: an educator's edited
    RELbot profile says `brake` on channel 3; a kill -9 in RUN leaves every PWM zero and channel
    3's digital output on, within the bound, and the alarm says so."""
    from xrflab import profiles as prof

    edited = prof.load_profile("relbot")
    edited["safety"] = {"reaction": "brake", "brake_channel": 3}
    saved = prof.save_profile(edited, server.data_dir)
    try:
        server.stop_run()
        run = server.start_run("relbot")
        ch = Channels.open(run["shm"], wait_s=5)
        try:
            with server.ws() as ws:
                drive_motors(ws)
                t_kill = time.monotonic()
                os.kill(run["pid"], signal.SIGKILL)
                safe_after = wait_forced_off(ch, t_kill)
                assert safe_after < 0.100, f"outputs safe only {safe_after * 1000:.1f} ms after the kill"
                alarm = ws.wait_type("alarm", kind="crash", timeout=5)
                assert alarm["safe_state"] == "sim outputs forced off but the brake on channel 3"
            sim = ch.shm.sim
            assert list(sim.pwm) == [0] * lib.XRF_MAX_CHANNELS and list(sim.dout) == _brake_only(3)
            assert list(sim.forced_dout) == _brake_only(3)
        finally:
            ch.close()
    finally:
        saved.unlink()
        server.stop_run()
