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
            assert ws.command("initialise")["accepted"]
            ws.wait_state("INITIALISED")
            assert ws.command("start")["accepted"]
            ws.wait_state("RUN")
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
