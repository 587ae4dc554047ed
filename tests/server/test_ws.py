"""The WebSocket protocol against a real appliance and a real relbot loop."""

from __future__ import annotations

import base64
import os
import socket
import time
from typing import Any

import pytest

from xrf_testing.harness import Server, WsClient, shared_builds_root, start_server, stop_server


def to_run(ws: WsClient) -> None:
    assert ws.command("initialise")["accepted"]
    ws.wait_state("INITIALISED")
    assert ws.command("start")["accepted"]
    ws.wait_state("RUN")


def test_new_client_gets_run_and_state(server: Server, running: dict[str, Any]) -> None:
    with server.ws() as ws:
        run = ws.wait_type("run")
        assert run["active"] and run["run"]["id"] == running["id"]
        assert [f["name"] for f in run["ros2xeno"]] == ["steer_left", "steer_right"]
        assert [f["name"] for f in run["xeno2ros"]] == ["pos_left", "pos_right"]
        state = ws.wait_type("state")
        assert state["name"] == "IDLE" and state["allowed"] == ["initialise"]


def test_commands_state_and_rejection(server: Server, running: dict[str, Any]) -> None:
    with server.ws() as ws:
        to_run(ws)
        # A command not allowed now reaches the loop, which rejects it with a reason.
        ack = ws.command("initialise")
        assert ack["accepted"] is False and "not allowed" in ack["reason"]
        state = ws.wait_for(lambda m: m["type"] == "state" and m.get("rejected"), seen=True)
        assert state["rejected"]["name"] == "initialise"
        assert "RUN" in state["rejected"]["reason"]
        assert set(state["allowed"]) == {"stop", "pause", "reset"}


def test_telemetry_rate_and_setpoint_following(server: Server, running: dict[str, Any]) -> None:
    """30 samples a second in 5 messages a second (Settings.telemetry_per_message = 6: each
    message costs the appliance a wake-up and a socket write per dashboard, issue 30 item 4),
    every message its samples oldest first, none sent twice, none due skipped."""
    with server.ws() as ws:
        to_run(ws)
        first = ws.wait_type("telemetry")
        assert set(first) == {"type", "run_id", "samples", "ros2xeno", "lost"}, set(first)
        assert {"enc", "pwm", "din", "dout", "cycle", "t", "t_ns", "xeno2ros"} <= set(first["samples"][0])
        # The rates on the loop's clock (the samples' t_ns), not on arrival: a test process that
        # fell behind on a busy machine reads a backlog at once (CI: 67 a second "arrived").
        t0 = time.monotonic()
        messages = [first]
        while time.monotonic() - t0 < 3.0:
            messages.append(ws.wait_type("telemetry"))
        assert all(len(m["samples"]) == 6 for m in messages), [len(m["samples"]) for m in messages]
        stamps = [s["t_ns"] for m in messages for s in m["samples"]]
        assert all(b > a for a, b in zip(stamps, stamps[1:])), "a sample sent twice or out of order"
        seconds = (stamps[-1] - stamps[0]) / 1e9
        samples_rate = (len(stamps) - 1) / seconds
        assert 25 <= samples_rate <= 35, samples_rate  # 30 Hz default, decimated from the loop's 50
        newest = [m["samples"][-1]["t_ns"] for m in messages]
        messages_rate = (len(newest) - 1) / ((newest[-1] - newest[0]) / 1e9)
        assert 4 <= messages_rate <= 6, messages_rate  # 5 a second: six samples each
        # No sample due skipped: the loop publishes every 20 ms, the samples due are 33 ms apart.
        assert max(b - a for a, b in zip(stamps, stamps[1:])) <= 60_000_000

        ws.send({"type": "setpoint", "fields": {"steer_left": 1.5, "steer_right": -0.5}})
        assert ws.wait_type("ack")["setpoint"] == {"steer_left": 1.5, "steer_right": -0.5}
        sample = ws.wait_sample(
            lambda s: abs(s["xeno2ros"]["pos_left"] - 1.5) < 0.1 and abs(s["xeno2ros"]["pos_right"] + 0.5) < 0.1,
            timeout=10,
        )
        assert any(sample["pwm"]) or sample["enc"] != [0, 0, 0, 0]
        # The message's Ros2Xeno is the loop's at its newest sample.
        assert ws.wait_type("telemetry")["ros2xeno"] == {"steer_left": 1.5, "steer_right": -0.5}


def test_timing_messages(server: Server, running: dict[str, Any]) -> None:
    with server.ws() as ws:
        timing = ws.wait_type("timing", timeout=3)
        assert timing["cycles"] > 0 and timing["cycle_freq"] == running["cycle_freq"]
        assert timing["stages"]["wakeup"]["count"] > 0
        assert len(timing["jitter"]["edges"]) == len(timing["jitter"]["counts"]) > 0
        assert {"wakeup", "fpga", "hook", "cycle"} <= set(timing["histograms"])
        assert sum(timing["histograms"]["cycle"]["counts"]) == timing["stages"]["cycle"]["count"]


def test_subscribe_filters_topics(server: Server, running: dict[str, Any]) -> None:
    with server.ws() as ws:
        ws.send({"type": "subscribe", "topics": ["state"]})
        ws.wait_type("ack")
        ws.messages.clear()
        assert ws.command("initialise")["accepted"]
        ws.wait_state("INITIALISED")
        deadline = time.monotonic() + 1.5
        while time.monotonic() < deadline:
            try:
                ws.wait_for(lambda m: False, timeout=0.2)
            except AssertionError:
                pass
        assert not [m for m in ws.messages if m["type"] in ("telemetry", "timing")]


BAD_INPUT = [
    ("not json at all", "malformed JSON"),
    ("[1, 2, 3]", "JSON object"),
    ('{"no": "type"}', "JSON object"),
    ('{"type": "launch"}', "unknown message type"),
    ('{"type": "command", "cmd": "fly"}', "unknown command"),
    ('{"type": "command"}', "command needs"),
    ('{"type": "command", "cmd": [1]}', "command needs"),
    ('{"type": "setpoint", "fields": {"warp": 9}}', "unknown field"),
    ('{"type": "setpoint", "fields": {"steer_left": "fast"}}', "not a number"),
    ('{"type": "setpoint", "fields": 3}', "setpoint needs"),
    ('{"type": "subscribe", "topics": ["gossip"]}', "unknown topic"),
    ('{"type": "setpoint", "fields": {"steer_left": 1e400}}', "finite"),
]


@pytest.mark.parametrize("frame,expect", BAD_INPUT)
def test_malformed_input_gets_an_error_and_nothing_breaks(
    server: Server, running: dict[str, Any], frame: str, expect: str
) -> None:
    with server.ws() as ws:
        ws.wait_type("state")
        ws.send(frame)
        reply = ws.wait_for(lambda m: m["type"] in ("error", "ack"))
        if expect:
            assert reply["type"] == "error" and expect in reply["error"], reply
        # Same connection still works, and the loop still cycles.
        ws.send({"type": "ping", "t": 1})
        assert ws.wait_type("pong")["t"] == 1
        assert ws.command("initialise")["accepted"]


def test_oversized_and_binary_frames(server: Server, running: dict[str, Any]) -> None:
    with server.ws() as ws:
        ws.wait_type("state")
        ws.send('{"type": "ping", "pad": "' + "x" * 100_000 + '"}')
        err = ws.wait_type("error")
        assert "limit" in err["error"]
        ws.send(b"\x00\x01\x02")
        assert "binary" in ws.wait_type("error")["error"]
        ws.send({"type": "ping", "t": 2})
        assert ws.wait_type("pong")["t"] == 2


def test_command_without_run_is_an_error(server: Server) -> None:
    server.stop_run()
    with server.ws() as ws:
        reply = ws.command("start")
        assert reply["type"] == "error" and "no run" in reply["error"]


def test_slow_client_is_dropped_others_unaffected(tmp_path) -> None:
    # Every loop publication to browsers (no decimation) and tight limits, so a client that
    # stops reading fills its socket, then its queue, within a few seconds.
    s = start_server(
        tmp_path,
        shared_builds_root(),
        telemetry_hz=0,
        client_queue_telemetry=8,
        slow_client_s=1.0,
        send_buffer_bytes=4096,
    )
    try:
        s.start_run("relbot")
        slow = _never_reading_client(int(s.url.rsplit(":", 1)[1]), s.http.cookies.get("xrf_session"))
        with s.ws() as fast:
            fast.wait_type("state")
            cycles: list[int] = []
            closed = False
            deadline = time.monotonic() + 40
            while time.monotonic() < deadline and not closed:
                m = fast.wait_type("telemetry")
                cycles.extend(sample["cycle"] for sample in m["samples"])
                if len(cycles) % 25 == 0:
                    closed = _clients(s) == 1  # only the fast one left
            assert closed, "slow client was not disconnected"
            # The fast client kept receiving throughout, with the loop's lost counter at zero.
            assert len(cycles) > 100
            assert all(b > a for a, b in zip(cycles, cycles[1:]))  # oldest first, none twice
            assert fast.wait_type("telemetry")["lost"] == 0
        slow.close()
    finally:
        stop_server(s)


def _never_reading_client(port: int, session: str) -> socket.socket:
    """A WebSocket handshake by hand and then silence: no library reader thread draining the
    socket behind our back, and a tiny receive buffer so the server's sends back up quickly."""
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 2048)  # before connect: sets the window
    sock.connect(("127.0.0.1", port))
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall(
        f"GET /ws HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
        f"Origin: http://127.0.0.1:{port}\r\nCookie: xrf_session={session}\r\n\r\n".encode()
    )
    head = b""
    while b"\r\n\r\n" not in head:
        head += sock.recv(1)
    assert head.startswith(b"HTTP/1.1 101"), head
    return sock


def _clients(s: Server) -> int:
    return int(s.http.get("/api/status").json()["clients"])
