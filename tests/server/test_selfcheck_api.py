"""The self-check and bench profiles through the appliance's API (issue 6, "Where"), against a
real appliance on the simulated RELbot bench: events over the WebSocket, reports kept and
exported, faults diagnosed, refusal over an active run, abort with the outputs zeroed, and the
profile editor's server-side validation."""

from __future__ import annotations

import json
import os
from typing import Any

import pytest

from xrf_testing.harness import Server, shared_builds_root, start_server, stop_server


def run_check(server: Server, ws: Any, timeout: float = 60, **body: Any) -> dict[str, Any]:
    """Start a check and return its final `selfcheck` message (event report or error)."""
    r = server.http.post("/api/selfcheck", json={"profile": "relbot", **body})
    assert r.status_code == 202, r.text
    check = r.json()["id"]
    return ws.wait_for(
        lambda m: m.get("type") == "selfcheck" and m.get("check") == check and m.get("event") in ("report", "error"),
        timeout=timeout,
    )


def test_check_on_the_simulated_relbot_events_report_saved_and_listed(server: Server) -> None:
    st = server.http.get("/api/selfcheck").json()
    assert st["bench"] == {"mode": "sim", "transport": "sim", "sim": "relbot", "device": ""}
    assert st["running"] is None and st["run_active"] is None
    with server.ws() as ws:
        final = run_check(server, ws)
        assert final["event"] == "report", final
        mine = [m for m in ws.messages if m.get("type") == "selfcheck" and m.get("check") == final["check"]]
        kinds = [m["event"] for m in mine]
        assert kinds[0] == "begin" and kinds[-1] == "report"
        assert {"start", "progress", "step", "end"} <= set(kinds)
        assert kinds.index("begin") < kinds.index("start") < kinds.index("step") < kinds.index("end")
        steps = [m for m in mine if m["event"] == "step"]
        assert [s["id"] for s in steps][:4] == ["spi", "init", "echo", "reset"]
    report = final["report"]
    assert report["verdict"] == "pass" and report["outputs_zeroed"] is True
    assert report["transport"] == "sim" and report["sim"] == "relbot" and report["bench"] == "relbot"
    # The link's timing step measures this machine's load: under a loaded (parallel) suite its
    # median may cross the warn line, a verdict the check gives for exactly that. Every other step
    # must pass.
    bad = [s for s in report["steps"] if s["status"] not in ("pass", "skipped")]
    assert all(s["id"] == "timing" and s["status"] == "warn" for s in bad), bad
    name = final["name"]
    listed = server.http.get("/api/selfcheck/reports").json()
    assert listed[0]["name"] == name and listed[0]["verdict"] == "pass" and listed[0]["bench"] == "relbot"
    assert listed[0]["started"] == report["started"] and listed[0]["outputs_zeroed"] is True
    assert (server.data_dir / "selfcheck" / f"{name}.json").is_file()
    got = server.http.get(f"/api/selfcheck/reports/{name}").json()
    assert got["verdict"] == "pass" and len(got["steps"]) == len(report["steps"])
    md = server.http.get(f"/api/selfcheck/reports/{name}/export", params={"fmt": "markdown"})
    assert md.status_code == 200 and md.headers["content-type"].startswith("text/markdown")
    assert f'filename="selfcheck-{name}.md"' in md.headers["content-disposition"]
    assert md.text.startswith("# Self-check: relbot bench — PASS")
    js = server.http.get(f"/api/selfcheck/reports/{name}/export", params={"fmt": "json"})
    assert json.loads(js.text)["verdict"] == "pass"
    assert server.http.get("/api/selfcheck/reports/..%2Fetc/export").status_code == 404
    assert server.http.get("/api/selfcheck/reports/nope").status_code == 404


def test_injected_fault_is_diagnosed(server: Server) -> None:
    with server.ws() as ws:
        final = run_check(server, ws, faults="dead_encoder=2")
    report = final["report"]
    assert report["verdict"] == "fail" and report["faults"] == "dead_encoder=2"
    failed = [s for s in report["steps"] if s["status"] == "fail"]
    assert [s["id"] for s in failed] == ["motor.2"]
    assert "encoder 2 does not count" in failed[0]["message"]
    assert "PMOD 2" in failed[0]["action"]
    assert report["outputs_zeroed"] is True


def test_faults_env_hook_on_a_simulated_bench(tmp_path_factory: pytest.TempPathFactory) -> None:
    """XRF_SELFCHECK_FAULTS in the appliance's environment applies to every check on the
    simulated bench (the hook tests use to break a bench)."""
    os.environ["XRF_SELFCHECK_FAULTS"] = "reversed_motor=1"
    try:
        s = start_server(tmp_path_factory.mktemp("data-faults"), shared_builds_root())
    finally:
        del os.environ["XRF_SELFCHECK_FAULTS"]
    try:
        with s.ws() as ws:
            final = run_check(s, ws)
        report = final["report"]
        assert report["faults"] == "reversed_motor=1"
        failed = [x for x in report["steps"] if x["status"] == "fail"]
        assert [x["id"] for x in failed] == ["motor.1"] and "wrong way" in failed[0]["message"]
    finally:
        stop_server(s)


def test_refused_while_a_run_is_active_unless_asked_to_stop_it(server: Server) -> None:
    server.stop_run()
    run = server.start_run("relbot")
    try:
        r = server.http.post("/api/selfcheck", json={"profile": "relbot"})
        assert r.status_code == 409
        assert "stop the run first" in r.json()["detail"] and f"run {run['id']}" in r.json()["detail"]
        assert server.http.get("/api/selfcheck").json()["run_active"]
        with server.ws() as ws:
            final = run_check(server, ws, stop_run=True)
        assert final["report"]["verdict"] == "pass"
        assert server.http.get("/api/status").json()["run_active"] is False
    finally:
        server.stop_run()


def test_abort_mid_check_zeroes_the_outputs(server: Server) -> None:
    with server.ws() as ws:
        r = server.http.post("/api/selfcheck", json={"profile": "relbot"})
        assert r.status_code == 202
        check = r.json()["id"]
        # Abort while motor 1 is being pulsed.
        ws.wait_for(
            lambda m: m.get("type") == "selfcheck" and m.get("event") == "progress" and m.get("step") == "motor.1",
            timeout=60,
        )
        again = server.http.post("/api/selfcheck", json={"profile": "relbot"})
        assert again.status_code == 409 and "already running" in again.json()["detail"]
        assert server.http.post("/api/selfcheck/abort").status_code == 200
        final = ws.wait_for(
            lambda m: m.get("type") == "selfcheck" and m.get("check") == check and m.get("event") == "report",
            timeout=30,
        )
    report = final["report"]
    assert report["verdict"] == "aborted" and report["outputs_zeroed"] is True
    assert server.http.post("/api/selfcheck/abort").status_code == 409
    listed = server.http.get("/api/selfcheck/reports").json()
    assert listed[0]["name"] == final["name"] and listed[0]["verdict"] == "aborted"


def test_profile_editor_validates_saves_and_resets(server: Server) -> None:
    names = {p["name"]: p for p in server.http.get("/api/profiles").json()}
    assert {"relbot", "jiwy"} <= set(names) and names["relbot"]["source"] == "default"
    got = server.http.get("/api/profiles/relbot").json()
    assert got["source"] == "default" and got["has_default"]
    profile = got["profile"]

    bad = json.loads(json.dumps(profile))
    bad["channels"][0]["duty"] = 0.5
    r = server.http.put("/api/profiles/relbot", json=bad)
    assert r.status_code == 422
    detail = r.json()["detail"]
    assert any(
        e["field"] == "channel 1.duty" and "out of range" in e["message"] and "at most 0.2" in e["message"]
        for e in detail["errors"]
    ), detail
    assert not (server.data_dir / "profiles" / "relbot.json").exists()
    # The field comes from the validator, also where the sentence does not start with it.
    bad = json.loads(json.dumps(profile))
    bad["channels"][0]["inputs"][1]["idle"] = 2
    r = server.http.put("/api/profiles/relbot", json=bad)
    assert r.status_code == 422
    assert [e["field"] for e in r.json()["detail"]["errors"]] == ["channel 1.inputs[1].idle"], r.json()
    assert (
        server.http.put(
            "/api/profiles/relbot", content=b"{not json", headers={"Content-Type": "application/json"}
        ).status_code
        == 422
    )
    r = server.http.put("/api/profiles/relbot", json={**profile, "name": "other"})
    assert r.status_code == 422 and r.json()["detail"]["errors"][0]["field"] == "name"

    edited = json.loads(json.dumps(profile))
    edited["title"] = "RELbot bench 3"
    r = server.http.put("/api/profiles/relbot", json=edited)
    assert r.status_code == 200 and r.json()["source"] == "edited"
    assert json.loads((server.data_dir / "profiles" / "relbot.json").read_text())["title"] == "RELbot bench 3"
    assert server.http.get("/api/profiles/relbot").json()["profile"]["title"] == "RELbot bench 3"

    r = server.http.delete("/api/profiles/relbot")
    assert r.status_code == 200 and r.json()["source"] == "default"
    assert r.json()["profile"]["title"] == profile["title"]
    assert server.http.delete("/api/profiles/relbot").status_code == 404


def test_system_page_api(server: Server) -> None:
    info = server.http.get("/api/system").json()
    assert info["version"] and info["data_dir"] == str(server.data_dir)
    assert info["disk"]["free"] > 0 and info["uptime_s"] >= 0
    assert info["bench"]["mode"] == "sim" and info["bench"]["transport"] == "sim"
    assert info["bench"]["backend"] in ("posix", "evl")
    doc = server.http.get("/api/system/doctor", timeout=60).json()
    ids = [c["id"] for c in doc["checks"]]
    assert ids == ["evl", "isolcpus", "governor", "throttling", "spi", "fpga", "clock", "disk", "ros2", "confinement"]
    assert all(c["status"] in ("ok", "warning", "failure", "not checked") for c in doc["checks"])
    assert sum(doc["counts"].values()) == len(ids)


def test_educator_only(server: Server) -> None:
    pw = server.create_user("obs1", role="observer")
    http, _ = server.login("obs1", pw)
    try:
        assert http.get("/api/selfcheck").status_code == 403
        assert http.post("/api/selfcheck", json={"profile": "relbot"}).status_code == 403
        assert http.get("/api/profiles").status_code == 403
        assert http.get("/api/system").status_code == 200  # the System page is for watchers too
    finally:
        http.close()
