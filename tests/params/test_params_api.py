"""Live tuning through the appliance (issue 28): the 20-sim template's parameters, found by the
build in its tokens file, listed, set atomically while it runs, confirmed with the cycle the loop
applied them at, refused whole when bad, logged as the run's change table, seen by watchers.

Real appliance, real build of the template (its sources unchanged), real loop on the simulated
RELbot: the PID's output limit set to 0 stops the motors from the confirmed cycle on.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from xrf_testing.harness import Server, shared_builds_root, start_server, stop_server, wait_for

KP = "PID1\\Kp"
LIMIT = "PID\\limit"


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    s = start_server(tmp_path_factory.mktemp("data"), shared_builds_root())
    yield s
    stop_server(s)


def _param(listing: dict[str, Any], name: str) -> dict[str, Any]:
    return next(p for p in listing["params"] if p["name"] == name)


def test_tune_20sim_template_while_it_runs(server: Server, tmp_path: Path) -> None:
    server.stop_run()
    assert server.http.get("/api/params").json()["note"] == "no run is active"
    with server.ws() as ws:
        ws.send({"type": "subscribe", "topics": ["state", "params", "telemetry"]})
        assert ws.wait_type("ack")["topics"]
        run = server.start_run("template-20sim")
        listing = server.http.get("/api/params").json()
        assert listing["origin"] == "20sim" and listing["run_id"] == run["id"]
        names = [p["name"] for p in listing["params"]]
        assert names == [KP, "PID1\\Ki", "PID1\\Kd", "PID2\\Kp", "PID2\\Ki", "PID2\\Kd", "PID\\tau_d", LIMIT]
        kp = _param(listing, KP)
        assert kp["value"] == 1.0 and kp["default"] == 1.0 and kp["unit"] == "-/rad" and not kp["has_range"]
        assert kp["min"] < 1.0 < kp["max"]
        assert server.http.get("/api/params/" + KP).json()["value"] == 1.0

        # A set before INITIALISING survives 20-sim's Initialize() (which writes the defaults).
        r = server.http.post("/api/params", json={"values": {KP: 2.0}})
        assert r.status_code == 200, r.text
        assert ws.command("initialise")["accepted"] and ws.wait_state("INITIALISED", 10)
        assert ws.command("start")["accepted"] and ws.wait_state("RUN", 5)
        ws.send({"type": "setpoint", "fields": {"steer_left": 1.0}})
        ws.wait_sample(lambda m: m["pwm"][0] != 0, 10)

        r = server.http.post("/api/params", json={"values": {LIMIT: 0.0, KP: 3.0}})
        assert r.status_code == 200, r.text
        body = r.json()
        cycle = body["cycle"]
        assert cycle > 0
        assert {(c["name"], c["old"], c["new"]) for c in body["changes"]} == {(LIMIT, 1.0, 0.0), (KP, 2.0, 3.0)}
        applied = ws.wait_for(
            lambda m: m.get("type") == "params" and m.get("event") == "applied" and m["cycle"] == cycle
        )
        assert applied["who"] == "admin"
        # From the confirmed cycle on the controller's output is limited to 0: no PWM.
        late = [ws.wait_sample(lambda m: m["cycle"] > cycle, 10) for _ in range(5)]
        assert all(m["pwm"][0] == 0 and m["pwm"][1] == 0 for m in late), late

        # Refused whole: nothing of a bad set lands.
        for bad, word in (
            ({KP: 4.0, "PID1\\\\nope": 1.0}, "unknown parameter"),
            ({KP: "4"}, "not a number"),
            ({KP: True}, "not a number"),
            ({KP: 1e9}, "out of range"),
            ({KP: math.inf}, "finite"),
            ({KP: math.nan}, "finite"),
        ):
            # json.dumps writes Infinity/NaN as a browser's JSON.parse would refuse, a script would not
            text = json.dumps({"values": bad})
            r = server.http.post("/api/params", content=text, headers={"Content-Type": "application/json"})
            assert r.status_code == 422, (bad, r.text)
            assert word in r.json()["detail"], (bad, r.json())
        assert server.http.get("/api/params/" + KP).json()["value"] == 3.0
        # A range the controller did not declare may be widened.
        r = server.http.post("/api/params", json={"values": {KP: 1e9}, "ranges": {KP: [0, 2e9]}})
        assert r.status_code == 200, r.text

        # Only the bench holder sets; a watcher sees.
        pw = server.create_user("watcher1", "student")
        other, _ = server.login("watcher1", pw)
        try:
            assert other.get("/api/params").json()["run_id"] == run["id"]
            r = other.post("/api/params", json={"values": {KP: 1.0}})
            assert r.status_code == 403, r.text
        finally:
            other.close()

        csv = server.http.get(f"/api/logs/runs/{run['id']}/param-changes", params={"fmt": "csv"}).text
        lines = csv.strip().splitlines()
        assert lines[0] == "run,cycle,t,name,old,new,who"
        assert any(f",{cycle}," in line and "PID\\limit,1.0,0.0,admin" in line for line in lines), csv
        assert len(lines) == 1 + 4  # KP before INITIALISING, LIMIT + KP, KP widened
        _changes_in_every_download(server, run["id"], cycle, tmp_path)
        _changes_in_the_live_rerun_stream(server, run["id"])

    server.stop_run()
    wait_for(lambda: server.http.get("/api/params").json()["run_id"] is None, 10, "the run's table dropped")
    r = server.http.post("/api/params", json={"values": {KP: 1.0}})
    assert r.status_code == 409 and "no loop is running" in r.json()["detail"], r.text


def _changes_in_every_download(server: Server, run_id: int, cycle: int, tmp: Path) -> None:
    """The change table inside each download of the run's log (docs/logging/decoding.md)."""
    import io
    import zipfile

    import pyarrow.parquet as pq
    from scipy.io import loadmat

    files = wait_for(lambda: server.http.get(f"/api/logs/runs/{run_id}").json()["files"], 10, "the run's log")
    url = f"/api/logs/runs/{run_id}/files/{files[0]['name']}"
    r = server.http.get(url, params={"fmt": "csv"})
    assert r.status_code == 200 and r.headers["content-type"] == "application/zip", r.headers
    assert r.headers["x-param-changes"] == "4" and ".zip" in r.headers["content-disposition"]
    with zipfile.ZipFile(io.BytesIO(r.content)) as z:
        samples, changes = z.namelist()
        assert z.read(samples).startswith(b"seq,cycle,t_ns,t_s,")
        table = z.read(changes).decode()
        assert f"{run_id},{cycle}," in table and "PID\\limit,1.0,0.0,admin" in table
    for fmt in ("mat", "parquet", "rrd"):
        r = server.http.get(url, params={"fmt": fmt})
        assert r.status_code == 200, (fmt, r.text)
        data = io.BytesIO(r.content)
        if fmt == "mat":
            pc = loadmat(data, simplify_cells=True)["param_changes"]
            assert list(pc["name"]).count(LIMIT) == 1 and cycle in list(pc["cycle"])
        elif fmt == "parquet":
            meta = json.loads(pq.read_schema(data).metadata[b"xrf.param_changes"])
            assert [(c["cycle"], c["new"]) for c in meta if c["name"] == LIMIT] == [(cycle, 0.0)]
        else:
            assert f"PID\\limit: 1 -> 0 at cycle {cycle} (admin)" in _rrd_texts(r.content, tmp)


def _changes_in_the_live_rerun_stream(server: Server, run_id: int) -> None:
    """A viewer of the run's live rerun recording gets an applied set as text log entries
    (params/changes) while connected (the proxy keeps only the recent past for late viewers)."""
    import threading

    from xrf_testing.grpcweb import READ_MESSAGES, read_messages
    from xrf_testing.rerun_stream import STORE_RECORDING, chunk_of

    wait_for(lambda: server.http.get("/api/logs/rerun").json()["live_run"] == run_id, 20, "the run's live proxy")
    texts: list[Any] = []
    answers: list[Any] = []
    setter = threading.Thread(  # once the viewer is connected (its first message)
        target=lambda: answers.append(server.http.post("/api/params", json={"values": {KP: 1.5, LIMIT: 0.5}}))
    )

    def on_message(payload: bytes) -> None:
        if not setter.ident:  # not started yet
            setter.start()
        chunk = chunk_of(payload)
        if chunk is not None and chunk.store_kind == STORE_RECORDING and chunk.entity == "/params/changes":
            texts.append(chunk)

    got = read_messages(server.http, READ_MESSAGES, on_message=on_message, timeout=30, until=lambda _: bool(texts))
    setter.join()
    assert answers[0].status_code == 200, answers[0].text
    assert got.ended_by == "until", (got.ended_by, len(texts))
    assert "TextLog:text" in texts[0].columns and texts[0].newest_time_ns, texts


def _rrd_texts(content: bytes, tmp: Path) -> list[str]:
    """The text log entries of an .rrd, read back with rerun's own reader."""
    from rerun.chunk import RrdReader

    path = tmp / "download.rrd"
    path.write_bytes(content)
    out = []
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        if "TextLog:text" in batch.schema.names:
            out += [t[0] for t in batch.column("TextLog:text").to_pylist()]
    return out


def test_declared_tunable_of_the_base_template(server: Server) -> None:
    """xrf::Tunable (xrf/tunable.hpp) in the base template: its declared range is the one
    enforced, and the value reaches the controller (Xeno2Ros echoes the setpoint times the gain)."""
    server.stop_run()
    with server.ws() as ws:
        ws.send({"type": "subscribe", "topics": ["state", "telemetry"]})
        assert ws.wait_type("ack")["topics"]
        server.start_run("template-base")
        listing = server.http.get("/api/params").json()
        assert listing["origin"] == "none"
        assert listing["params"] == [
            {
                "name": "echo.gain",
                "unit": "-",
                "default": 1.0,
                "min": -10.0,
                "max": 10.0,
                "has_range": True,
                "value": 1.0,
                "source": "declared",
            }
        ]
        assert ws.command("initialise")["accepted"] and ws.wait_state("INITIALISED", 10)
        assert ws.command("start")["accepted"] and ws.wait_state("RUN", 10)
        ws.send({"type": "setpoint", "fields": {"steer_left": 0.5}})
        ws.wait_sample(lambda m: m["xeno2ros"].get("pos_left") == 0.5, 10)
        r = server.http.post("/api/params", json={"values": {"echo.gain": 10.5}})
        assert r.status_code == 422 and "out of range -10 .. 10" in r.json()["detail"], r.text
        r = server.http.post("/api/params", json={"values": {"echo.gain": 3.0}, "ranges": {"echo.gain": [-20, 20]}})
        assert r.status_code == 422 and "its range is the controller's" in r.json()["detail"], r.text
        r = server.http.post("/api/params", json={"values": {"echo.gain": -4.0}})
        assert r.status_code == 200, r.text
        cycle = r.json()["cycle"]
        late = ws.wait_sample(lambda m: m["cycle"] > cycle, 10)
        assert late["xeno2ros"]["pos_left"] == -2.0
    server.stop_run()


def test_a_controller_without_parameters_says_why(server: Server) -> None:
    server.stop_run()
    server.start_run("relbot")
    listing = server.http.get("/api/params").json()
    assert listing["params"] == [] and "declares no tunable parameters" in listing["note"]
    r = server.http.post("/api/params", json={"values": {"kp": 1.0}})
    assert r.status_code == 422 and "declares no tunable parameters" in r.json()["detail"], r.text
    server.stop_run()
