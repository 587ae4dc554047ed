"""Every message /ws sends in a realistic session matches the schema the appliance publishes
(GET /api/ws-schema, xrflab/server/ws/messages.py), and bad incoming messages get a clear error
(issue 20)."""

from __future__ import annotations

import os
import signal
from typing import Any

import httpx
from jsonschema import Draft202012Validator

from xrf_testing.harness import Server, WsClient
from xrflab.server.http import runs as api
from xrflab.server.ws import hub, messages


def validator(schema: dict[str, Any], direction: str) -> Draft202012Validator:
    """The direction's oneOf, with the shared $defs it refers to (#/$defs/...)."""
    return Draft202012Validator({**schema[direction], "$defs": schema["$defs"]})


def drain(ws: WsClient, timeout: float = 0.5) -> None:
    """Take in whatever is still on its way."""
    try:
        ws.wait_for(lambda m: False, timeout=timeout)
    except AssertionError:
        pass


def test_every_message_of_a_session_matches_the_published_schema(server: Server) -> None:
    r = server.http.get("/api/ws-schema")
    assert r.status_code == 200, r.text
    schema = r.json()
    assert httpx.get(server.url + "/api/ws-schema").status_code == 401  # behind the login
    Draft202012Validator.check_schema(schema)
    assert schema["kinds"]["server"] == list(messages.SERVER_KINDS)
    assert set(schema["kinds"]["client"]) == set(api.WS_PERMS)
    assert set(schema["topics"]) == set(hub.TOPICS) <= set(schema["kinds"]["server"])
    server_v, client_v = validator(schema, "server"), validator(schema, "client")

    # Three audiences: the educator, the student who drives, an observer (redacted messages).
    server.stop_run()
    student_pw = server.create_user("schema_student", "student")
    observer_pw = server.create_user("schema_observer", "observer")
    student_http, student_ws = server.login("schema_student", student_pw)
    _, observer_ws = server.login("schema_observer", observer_pw)
    with server.ws() as edu, student_ws() as ws, observer_ws() as obs:
        clients = (edu, ws, obs)
        ws.wait_type("lease")  # a new client's snapshot: run, state, lease, ros
        assert student_http.post("/api/lease/take").status_code == 200
        ws.wait_type("lease", event="take")
        r = student_http.post("/api/runs", json={"build": "relbot"}, timeout=300)
        assert r.status_code == 201, r.text
        run = r.json()
        ws.wait_type("run", event="started", timeout=10)
        assert obs.wait_type("run", event="started", timeout=10)["redacted"] is True

        # Drive it: commands, a rejection, setpoints, subscribe, ping.
        for cmd, state in [("initialise", "INITIALISED"), ("start", "RUN")]:
            assert ws.command(cmd)["accepted"]
            ws.wait_state(state)
        assert ws.command("initialise")["accepted"] is False
        ws.send({"type": "setpoint", "fields": {"steer_left": 1.5, "steer_right": -0.5}, "id": 3})
        assert ws.wait_type("ack", id=3)["setpoint"] == {"steer_left": 1.5, "steer_right": -0.5}
        ws.wait_type("telemetry")
        edu.wait_type("timing", timeout=3)
        assert ws.command("pause")["accepted"]
        ws.wait_state("PAUSED")
        assert ws.command(2)["accepted"]  # start by number
        ws.wait_state("RUN")
        obs.send({"type": "subscribe", "topics": ["state", "alarm", "run", "lease"]})
        obs.wait_type("ack")
        ws.send({"type": "ping", "t": 5, "id": "p"})
        assert ws.wait_type("pong")["t"] == 5

        # Refusals: each a clear `error` naming what was wrong, the connection carries on.
        bad = [
            ({"type": "warp", "id": 1}, "unknown message type 'warp'; types: command, setpoint, subscribe, ping"),
            ({"type": "command", "cmd": True}, "command needs 'cmd': a command name or number"),
            ({"type": "command", "cmd": "fly"}, "unknown command 'fly'"),
            ({"type": "setpoint", "fields": []}, "setpoint needs 'fields'"),
            ({"type": "setpoint", "fields": {"steer_left": {"deep": 1}}}, "is not a number"),
            ({"type": "subscribe", "topics": "state"}, "subscribe needs 'topics'"),
            ({"type": "subscribe", "topics": ["state", "gossip"]}, "unknown topic(s) gossip"),
        ]
        for frame, expect in bad:
            assert client_v.is_valid(frame) is False or frame["type"] == "command", frame  # the schema says so too
            ws.send(frame)
            err = ws.wait_for(lambda m: m["type"] in ("error", "ack"))
            assert err["type"] == "error" and expect in err["error"], (frame, err)
            assert err["request"] == frame["type"]
        obs.send({"type": "setpoint", "fields": {"steer_left": 1}})
        assert obs.wait_type("error")["denied"] is True

        # What the browsers send validates too (the dashboard's messages).
        for frame in (
            {"type": "command", "cmd": "start"},
            {"type": "command", "cmd": 3},
            {"type": "setpoint", "fields": {"a": 1.0, "b": True, "c": [1, 2]}},
            {"type": "subscribe", "topics": ["state"]},
            {"type": "ping", "t": 1},
        ):
            client_v.validate(frame)

        # A crash: kill -9 the controller mid-run (alarm, run ended, state inactive).
        os.kill(run["pid"], signal.SIGKILL)
        for c in clients:
            c.wait_type("alarm", kind="crash", timeout=10)
        ws.wait_type("run", event="ended", timeout=10)

        # A lease change: released (the run's end keeps it), then taken by the educator.
        assert student_http.post("/api/lease/release").status_code == 200
        ws.wait_type("lease", event="released")
        assert server.http.post("/api/lease/take").status_code == 200
        edu.wait_type("lease", event="take")
        assert server.http.post("/api/lease/release").status_code == 200
        for c in clients:
            drain(c)

    student_http.close()
    kinds: set[str] = set()
    for c in clients:
        for m in c.messages:
            if not server_v.is_valid(m):  # say where, from the kind's own definition
                ref = schema["server"]["discriminator"]["mapping"].get(m.get("type"), "#/$defs/none")
                errors = list(Draft202012Validator({"$ref": ref, "$defs": schema["$defs"]}).iter_errors(m))
                where = [f"{'.'.join(map(str, e.absolute_path))}: {e.message}" for e in errors]
                raise AssertionError(f"{m.get('type')} does not match the schema: {where}\n{m}")
            kinds.add(m["type"])
    assert kinds >= {"state", "run", "telemetry", "timing", "alarm", "lease", "ros", "ack", "pong", "error"}, kinds
    # The same messages through the pydantic models the schema comes from.
    for m in edu.messages:
        messages.SERVER_KINDS[m["type"]].model_validate(m)


def test_unknown_kind_is_refused_before_its_fields(server: Server) -> None:
    with server.ws() as ws:
        ws.send({"type": "setpoints", "fields": {"x": 1}, "id": 9})
        err = ws.wait_type("error")
        assert err["id"] == 9 and "unknown message type 'setpoints'" in err["error"]
        ws.send({"type": "ping", "t": 1})
        assert ws.wait_type("pong")["t"] == 1  # and the connection carries on
