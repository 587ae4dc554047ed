"""A real appliance enrolled in a room (its enrolment file written as `xrf room join` would)
publishes its status, events and last will through a real mosquitto; the broker killed and
restarted; stale states never win."""

from __future__ import annotations

import json
import os
import signal
import time

from xrf_testing.harness import shared_builds_root, start_server, stop_server, wait_for
from xrf_testing.room_support import Recorder, room_endpoint
from xrflab.room import sso, topics
from xrflab.room.enrol import Enrolment, write_enrolment


def _status(rec: Recorder, name: str) -> list[dict]:
    return [json.loads(p) for t, p, _ in rec.messages if t == topics.bench(name, "status")]


def _events(rec: Recorder, name: str) -> list[dict]:
    return [json.loads(p) for t, p, _ in rec.messages if t == topics.bench(name, "event")]


def _enrol(files, data_dir, name: str) -> None:
    pw = f"pw-{name}-{os.urandom(6).hex()}"
    files.set_password(name, pw)
    files.reload()
    write_enrolment(
        data_dir,
        Enrolment.model_validate(
            {
                "name": name,
                "broker": {"host": "127.0.0.1", "port": files.port, "username": name, "password": pw},
                "room_key": sso.public_text(sso.new_private_key()),
                "bench_key": sso.private_text(sso.new_private_key()),
            }
        ),
    )


def test_status_events_will_and_broker_restart(broker, tmp_path) -> None:
    files = broker.files
    data = tmp_path / "bench"
    data.mkdir()
    room = Recorder(room_endpoint(files), "room", [topics.BENCH_ALL], listens=True)
    assert room.wait_connected()
    _enrol(files, data, "b1")
    server = start_server(data, shared_builds_root())
    try:
        # online (retained) and a first status, with the machine's facts
        room.wait_message(lambda t, p: t == topics.bench("b1", "online") and json.loads(p)["online"], 10)
        st = wait_for(lambda: _status(room, "b1"), 10, "a status")[-1]
        assert st["state"] == "NO RUN" and st["boot"] > 0 and st["disk_free_mb"] > 0
        assert "url" not in st  # where a bench is, the room knows from its enrolment, not from it
        # a run: the state and the run_started event arrive; status every second carries cycles
        server.start_run("relbot")
        wait_for(lambda: any(e["kind"] == "run_started" for e in _events(room, "b1")), 30, "run_started")
        with server.ws() as ws:
            assert ws.command("initialise")["accepted"]
            ws.wait_state("INITIALISED", 10)
            assert ws.command("start")["accepted"]
            ws.wait_state("RUN", 10)
        wait_for(
            lambda: any(s["state"] == "RUN" and (s.get("cycle_rate") or 0) > 100 for s in _status(room, "b1")),
            10,
            "RUN with a cycle rate",
        )
        seqs = [(s["boot"], s["seq"]) for s in _status(room, "b1")]
        assert seqs == sorted(seqs)  # (boot, seq) only grows

        # the broker dies: the bench runs on, its events wait; nothing stops
        broker.kill()
        # no wait for the bench to notice: an event sent into the dead connection stays queued
        # until acknowledged (publisher._inflight), so the next lines hold either way
        r = server.http.post("/api/runs/current/stop", timeout=30)
        assert r.status_code == 200
        room.close()
        broker.start()
        # the bench is back before the room: it holds its events (a restarted broker has no
        # subscriptions; QoS 1 to nobody would be acknowledged and lost) and says so on its tile
        watch = Recorder(room_endpoint(files), "watch", [topics.BENCH_ALL])
        assert watch.wait_connected()
        wait_for(
            lambda: any(s["state"] != "RUN" and s["events_queued"] >= 1 for s in _status(watch, "b1")),
            15,
            "a status with the events held",
        )
        assert not _events(watch, "b1")
        watch.close()
        room2 = Recorder(room_endpoint(files), "room2", [topics.BENCH_ALL], listens=True)
        assert room2.wait_connected()
        # the queued run_ended arrives after the restart, and the retained status is the newest
        wait_for(lambda: any(e["kind"] == "run_ended" for e in _events(room2, "b1")), 15, "queued run_ended")
        wait_for(lambda: any(s["state"] != "RUN" for s in _status(room2, "b1")), 10, "status after restart")
        after = _status(room2, "b1")[-1]
        assert (after["boot"], after["seq"]) > seqs[-1]

        # the appliance dies (kill -9): the broker publishes its last will within 5 s
        t0 = time.monotonic()
        server.proc.send_signal(signal.SIGKILL)
        server.proc.wait()
        room2.wait_message(lambda t, p: t == topics.bench("b1", "online") and not json.loads(p)["online"], 5)
        assert time.monotonic() - t0 < 5
        room2.close()
    finally:
        if server.proc.poll() is None:
            stop_server(server)
        else:
            server.http.close()
            # the killed appliance's loop is ended by the session's cleanup of the run sandbox
        room.close()
