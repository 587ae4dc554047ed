"""The dashboards' streams cost nothing while nobody reads them (issue 30: the appliance's idle
footprint): with no WebSocket client the reader builds no telemetry messages and the timing task
no histograms; they resume as soon as a client connects. A real appliance, a real RELbot loop
at 1 kHz, real WebSockets; the loop's progress is read from its shared memory (no client)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from xrf_testing.harness import Server, shared_builds_root, start_server, stop_server
from xrflab.channels import Channels

TELEMETRY_HZ = 30  # the appliance's default telemetry_hz


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    s = start_server(Path(tmp_path_factory.mktemp("data")), shared_builds_root())
    yield s
    stop_server(s)


def wait_cycles(ch: Channels, n: int, timeout: float = 30.0) -> None:
    """Until the loop has run n more cycles (its status block, read directly)."""
    start = ch.status().cycles
    deadline = time.monotonic() + timeout
    while ch.status().cycles < start + n:
        assert time.monotonic() < deadline, "the loop did not advance"
        time.sleep(0.05)


def test_no_telemetry_built_without_a_client_and_it_resumes_for_one(server: Server) -> None:
    run = server.start_run("relbot")
    ch = Channels.open(run["shm"], wait_s=10)
    try:
        with server.ws() as ws:
            ws.to_run()
            ws.wait_type("telemetry")  # the stream runs while a client is connected
            before = ws.wait_type("timing", 5)["telemetry_sent"]
        # Nobody connected for 6 s of the loop's time: at 30 Hz a stream built for nobody would
        # count 180 more messages.
        wait_clients_gone(server)
        wait_cycles(ch, 6000)
        assert ch.status().state_name == "RUN"
        with server.ws() as ws:
            # It resumes for the new client: samples arrive and the count grows again.
            ws.wait_type("telemetry", 5)
            first = ws.wait_type("timing", 5)["telemetry_sent"]
            second = ws.wait_for(lambda m: m["type"] == "timing" and m["telemetry_sent"] > first, timeout=5)
        # What was sent between the two connections: the tail of the first client's second and
        # the new client's first ~1-2 s, far below the 6 s of the stream nobody read.
        sent_meanwhile = first - before
        assert sent_meanwhile < 3.5 * TELEMETRY_HZ, (before, first)
        assert second["telemetry_sent"] > first
    finally:
        ch.close()
        server.stop_run()


def wait_clients_gone(server: Server, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while server.http.get("/api/status").json()["clients"] != 0:
        assert time.monotonic() < deadline, "the closed WebSocket stayed registered"
        time.sleep(0.05)


def test_nobody_connected_no_host_waits_on_the_doorbell_and_no_sample_is_lost(server: Server) -> None:
    """With no client the appliance reads the run's rings on a timer a quarter of their fill time
    apart (server/runs/reader.py) and drains the log ring likewise (logs/host_writer.py): no
    thread of it waits on the doorbell, so the loop rings it for nobody (no system call), and
    still every telemetry sample reaches the 3D view's recording and every record the log."""
    from xrflab.channels.binding import ffi, lib
    from xrflab.viz.recorder import load_recording

    wait_clients_gone(server)
    run = server.start_run("relbot")
    ch = Channels.open(run["shm"], wait_s=10)
    try:
        for cmd in ("initialise", "start"):
            assert server.http.post("/api/runs/current/command", json={"cmd": cmd}).json()["accepted"]
        wait_cycles(ch, 1500)  # the reader has seen the telemetry's rate and slowed down
        waiting = []
        for _ in range(100):
            waiting.append(lib.xrfpy_load_u32(ffi.addressof(ch.shm, "doorbell_waiters")))
            time.sleep(0.01)  # sampling the word over a second: time passing is the point
        # Before: the doorbell thread and the log writer sat in the futex nearly all the time.
        assert sum(1 for w in waiting if w) <= 5, waiting
        wait_cycles(ch, 3000)
        freq = ch.info["cycle_freq"]
    finally:
        ch.close()
        server.stop_run()
    row = server.http.get(f"/api/runs/{run['id']}").json()
    assert row["log_lost"] == 0 and row["log_records"] >= 4000
    rec = load_recording(Path(row["run_dir"]))
    steps = {b - a for a, b in zip(rec.cycle, rec.cycle[1:])}
    # RELbot publishes telemetry every 20th cycle (50 Hz at 1 kHz): the recording has each one,
    # no gap (a sample overwritten unread would show as a step of 40 or more).
    assert freq == 1000 and steps == {20}, sorted(steps)[:10]
    assert len(rec) >= 4500 / 20


def test_with_a_dashboard_the_reader_wakes_itself_for_the_samples_sent(server: Server) -> None:
    """With a client taking telemetry the reader wakes on its own clock just after the loop
    publishes the next sample due (server/runs/reader.py, `next_publication`): no thread of the
    appliance sits in the doorbell's futex for the samples the decimation skips (before: the
    doorbell thread waited there all the time and woke for all 50 a second), and the client still
    gets a steady 30 samples a second, every sample due (steps of 33.3 ms on the loop's clock,
    within the loop's publication spacing of 20 ms), in 5 messages a second of six."""
    from xrflab.channels.binding import ffi, lib

    wait_clients_gone(server)
    run = server.start_run("relbot")
    ch = Channels.open(run["shm"], wait_s=10)
    try:
        with server.ws() as ws:
            ws.to_run()
            ws.wait_type("telemetry")
            waiting = []
            got = []
            newest = []
            t_end = time.monotonic() + 2.0
            while time.monotonic() < t_end:
                waiting.append(lib.xrfpy_load_u32(ffi.addressof(ch.shm, "doorbell_waiters")))
                samples = ws.wait_type("telemetry", 5)["samples"]
                got += [s["t_ns"] for s in samples]
                newest.append(samples[-1]["t_ns"])
        # The doorbell is the fallback for a late sample only (a busy core): rarely waited on.
        assert sum(1 for w in waiting if w) <= len(waiting) // 4, waiting
        rate = (len(got) - 1) / ((got[-1] - got[0]) / 1e9)
        assert 25 <= rate <= 35, rate
        messages = (len(newest) - 1) / ((newest[-1] - newest[0]) / 1e9)
        assert 4 <= messages <= 6, messages  # 5 a second: six samples each
        steps = [b - a for a, b in zip(got, got[1:])]
        assert max(steps) <= 60_000_000, steps  # no sample due skipped (one would leave a 53 ms+ step)
    finally:
        ch.close()
        server.stop_run()


def test_a_client_without_telemetry_gets_the_state_on_the_readers_own_clock(server: Server) -> None:
    """A client taking the state and monitor lines but not telemetry (a hidden dashboard tab,
    frontend/app.js followVisibility; a tool): the reader wakes on its own clock, 10 times a
    second (server/runs/reader.py, STREAMS_PERIOD_S), not for every publication of the loop on
    the doorbell (before: the doorbell thread sat in the futex and woke the reader 50 times a
    second, more than a visible dashboard's 15), and the state still reaches the client."""
    from xrflab.channels.binding import ffi, lib

    wait_clients_gone(server)
    run = server.start_run("relbot")
    ch = Channels.open(run["shm"], wait_s=10)
    try:
        with server.ws() as ws:
            ws.send({"type": "subscribe", "topics": ["state", "monitor", "run", "alarm", "timing"]})
            assert "telemetry" not in ws.wait_type("ack")["topics"]
            ws.to_run()
            wait_cycles(ch, 500)
            waiting = []
            for _ in range(100):
                waiting.append(lib.xrfpy_load_u32(ffi.addressof(ch.shm, "doorbell_waiters")))
                time.sleep(0.01)  # sampling the word over a second: time passing is the point
            assert sum(1 for w in waiting if w) <= len(waiting) // 4, waiting
            assert ws.command("pause")["accepted"]
            ws.wait_state("PAUSED")
            assert ws.command("start")["accepted"]
            ws.wait_state("RUN")
            assert not [m for m in ws.messages if m["type"] == "telemetry"]
    finally:
        ch.close()
        server.stop_run()
