"""Bad input against a real appliance: each refused with the right status and nothing changed.
Wrong password, expired session, forged cookie, cross-site WebSocket, CSRF, a student commanding
without the lease, guessing another's run ids, an observer uploading; disabled accounts, API
tokens, one-time passwords, class lists and the audit trail."""

from __future__ import annotations

import io
import time
import zipfile

import httpx
import pytest
from websockets.exceptions import ConnectionClosed, InvalidStatus

from xrf_testing.accounts_support import Account, make_account
from xrf_testing.harness import (
    ADMIN_PASSWORD,
    Server,
    login_client,
    shared_builds_root,
    start_server,
    stop_server,
    ws_connect,
)


def anon(server: Server, **headers: str) -> httpx.Client:
    return httpx.Client(base_url=server.url, headers={"Origin": server.url, **headers}, timeout=30)


# ---- login, sessions, cookies ---------------------------------------------------------------------


def test_wrong_password_and_unknown_user(server: Server, accounts: dict[str, Account]) -> None:
    with anon(server) as c:
        for body in (
            {"username": "student", "password": "not the password"},
            {"username": "nobody-here", "password": "whatever-123"},
        ):
            r = c.post("/api/auth/login", json=body)
            assert r.status_code == 401 and r.json()["detail"] == "wrong username or password"  # same for both
            assert "xrf_session" not in r.cookies
        assert c.get("/api/me").status_code == 401


def test_cookies_are_httponly_samesite_strict(server: Server, accounts: dict[str, Account]) -> None:
    with anon(server) as c:
        r = c.post("/api/auth/login", json={"username": "observer", "password": accounts["observer"].password})
        assert r.status_code == 200
        cookies = r.headers.get_list("set-cookie")
        session = next(h for h in cookies if h.startswith("xrf_session="))
        assert "HttpOnly" in session and "SameSite=strict" in session.replace("Strict", "strict")
        assert "Secure" not in session  # plain http here; https sets it
        csrf = next(h for h in cookies if h.startswith("xrf_csrf="))
        assert "HttpOnly" not in csrf and r.json()["csrf"] in csrf


def test_forged_and_garbage_cookies_are_refused(server: Server) -> None:
    real = server.http.cookies.get("xrf_session")
    forged = real[:-4] + ("AAAA" if not real.endswith("AAAA") else "BBBB")
    for value in (forged, "x" * 43, "", "admin", "' OR 1=1 --", "%00" * 50):
        with httpx.Client(base_url=server.url, cookies={"xrf_session": value}, timeout=30) as c:
            assert c.get("/api/bench").status_code == 401, value
            assert c.get("/api/me").status_code == 401
    with httpx.Client(base_url=server.url, headers={"Authorization": "Bearer xrf_forged"}, timeout=30) as c:
        assert c.get("/api/bench").status_code == 401


def test_logged_out_browser_gets_the_login_page(server: Server) -> None:
    with anon(server) as c:
        r = c.get("/")
        assert r.status_code == 303 and r.headers["location"] == "/login"
        assert c.get("/login").status_code == 200 and "login-form" in c.get("/login").text
        assert c.get("/static/app.js").status_code == 200  # code, no data
        assert c.get("/api/health").json() == {"ok": True}
        for path in ("/api/bench", "/api/runs", "/openapi.json", "/docs", "/api/lease"):
            assert c.get(path).status_code == 401, path


def test_security_headers(server: Server) -> None:
    for path in ("/login", "/api/health", "/static/app.js"):
        h = server.http.get(path).headers
        assert h["x-content-type-options"] == "nosniff" and h["x-frame-options"] == "SAMEORIGIN", path
        assert h["referrer-policy"] == "same-origin"


def test_logout_ends_the_session(server: Server) -> None:
    http = login_client(server.url, "admin", ADMIN_PASSWORD)
    token = http.cookies.get("xrf_session")
    assert http.post("/api/auth/logout").status_code == 204
    with httpx.Client(base_url=server.url, cookies={"xrf_session": token}, timeout=30) as c:
        assert c.get("/api/me").status_code == 401  # the old cookie is dead on the server, not just deleted
    http.close()


def test_expired_and_idle_sessions(tmp_path) -> None:
    s = start_server(tmp_path, shared_builds_root(), session_idle_s=1.2, session_max_s=4.0)
    try:
        # Idle: unused for longer than session_idle_s.
        idle = login_client(s.url, "admin", ADMIN_PASSWORD)
        assert idle.get("/api/me").status_code == 200
        time.sleep(1.5)  # the point: idle longer than session_idle_s
        assert idle.get("/api/me").status_code == 401
        # Absolute: used all the time, still over after session_max_s.
        busy = login_client(s.url, "admin", ADMIN_PASSWORD)
        t0 = time.monotonic()
        while time.monotonic() - t0 < 2.5:  # longer than the idle timeout: use keeps it alive
            assert busy.get("/api/me").status_code == 200
            time.sleep(0.25)
        while time.monotonic() - t0 < 4.2:
            busy.get("/api/me")
            time.sleep(0.25)
        assert busy.get("/api/me").status_code == 401
        with pytest.raises(InvalidStatus):
            ws_connect(s.ws_url, busy)
    finally:
        stop_server(s)


# ---- CSRF and origins -----------------------------------------------------------------------------


def _users(server: Server) -> set[str]:
    return {u["username"] for u in server.http.get("/api/users").json()}


def test_csrf_token_and_origin_are_required(server: Server) -> None:
    cookies = {"xrf_session": server.http.cookies.get("xrf_session")}
    token = server.http.headers["X-CSRF-Token"]
    body = {"username": "csrf-victim", "role": "educator", "password": "long enough pw"}
    attempts = [
        ({"Origin": server.url}, "no token"),
        ({"Origin": server.url, "X-CSRF-Token": "wrong" + token}, "wrong token"),
        ({"Origin": "http://evil.example", "X-CSRF-Token": token}, "foreign origin"),
        ({"Referer": "http://evil.example/page", "X-CSRF-Token": token}, "foreign referer"),
        ({"X-CSRF-Token": token}, "neither Origin nor Referer"),
        ({"Origin": "null", "X-CSRF-Token": token}, "opaque origin"),
    ]
    for headers, why in attempts:
        with httpx.Client(base_url=server.url, cookies=cookies, headers=headers, timeout=30) as c:
            r = c.post("/api/users", json=body)
            assert r.status_code == 403, (why, r.status_code, r.text)
    assert "csrf-victim" not in _users(server)  # nothing changed
    # Same-origin Referer (some browsers omit Origin) with the token is fine.
    with httpx.Client(
        base_url=server.url,
        cookies=cookies,
        timeout=30,
        headers={"Referer": server.url + "/#users", "X-CSRF-Token": token},
    ) as c:
        assert c.post("/api/users", json={**body, "username": "csrf-ok", "role": "observer"}).status_code == 201


def test_login_from_a_foreign_page_is_refused(server: Server, accounts: dict[str, Account]) -> None:
    with httpx.Client(base_url=server.url, headers={"Origin": "http://evil.example"}, timeout=30) as c:
        r = c.post("/api/auth/login", json={"username": "student", "password": accounts["student"].password})
        assert r.status_code == 403 and "xrf_session" not in r.cookies


def test_cross_site_websocket_is_refused(server: Server, accounts: dict[str, Account]) -> None:
    for origin in ("http://evil.example", "http://127.0.0.1:1", "null"):
        with pytest.raises(InvalidStatus) as exc:
            server.ws(origin=origin)
        assert exc.value.response.status_code == 403
    with pytest.raises(InvalidStatus):  # a cookie without any Origin: not a browser page of ours
        server.ws(origin=None)
    with pytest.raises(InvalidStatus):  # no session at all
        from websockets.sync.client import connect

        connect(server.ws_url, origin=server.url)
    with server.ws() as ws:  # the right origin and a session
        ws.wait_type("state")


def test_allowed_origins_setting(tmp_path) -> None:
    s = start_server(tmp_path, shared_builds_root(), allow_origins=["https://lab.example.edu"])
    try:
        cookies = {"xrf_session": s.http.cookies.get("xrf_session")}
        headers = {"Origin": "https://lab.example.edu", "X-CSRF-Token": s.http.headers["X-CSRF-Token"]}
        with httpx.Client(base_url=s.url, cookies=cookies, headers=headers, timeout=30) as c:
            assert c.post("/api/lease/take").status_code == 200
        with s.ws(origin="https://lab.example.edu") as ws:
            ws.wait_type("lease")
    finally:
        stop_server(s)


# ---- roles, the lease, ownership ------------------------------------------------------------------


def test_student_without_the_lease_cannot_drive(server: Server, accounts: dict[str, Account], free_bench: None) -> None:
    student = accounts["student"]
    run = server.start_run("relbot")  # the educator's run, bench lease free
    assert student.http.post("/api/runs/current/command", json={"cmd": "initialise"}).status_code == 403
    assert student.http.post("/api/runs/current/stop").status_code == 403
    assert student.http.post("/api/runs", json={"build": "relbot"}).status_code == 403
    with student.ws() as ws:
        ws.wait_state("IDLE")
        reply = ws.command("initialise")
        assert reply["type"] == "error" and reply["denied"] and "do not hold the bench" in reply["error"]
        ws.send({"type": "setpoint", "fields": {"steer_left": 1.0}})
        reply = ws.wait_type("error")
        assert "do not hold the bench" in reply["error"]
        ws.send({"type": "ping", "t": 1})  # watching is fine
        ws.wait_type("pong")
    status = server.http.get(f"/api/runs/{run['id']}").json()
    assert status["status"] == "running" and status["state"] in ("", "IDLE")  # nothing changed
    with server.ws() as ws:
        assert ws.wait_type("run")["setpoint"] == {}
        assert ws.wait_type("state", seen=True)["name"] == "IDLE"


def test_stop_is_the_safety_exception(server: Server, accounts: dict[str, Account], free_bench: None) -> None:
    """Any student (lease or not) may stop or pause a running controller; observers may not."""
    server.start_run("relbot")
    with server.ws() as edu:
        assert edu.command("initialise")["accepted"]
        edu.wait_state("INITIALISED")
        assert edu.command("start")["accepted"]
        edu.wait_state("RUN")
    with accounts["observer"].ws() as obs:
        reply = obs.command("stop")
        assert reply["type"] == "error" and "observers may not" in reply["error"]
    assert accounts["observer"].http.post("/api/runs/current/command", json={"cmd": "stop"}).status_code == 403
    with accounts["student2"].ws() as ws:
        reply = ws.command("pause")
        assert reply["type"] == "ack" and reply["accepted"], reply
        ws.wait_state("PAUSED")
        r = accounts["student2"].http.post("/api/runs/current/command", json={"cmd": "stop"})
        assert r.status_code == 200 and r.json()["accepted"]
        ws.wait_state("STOPPED")
        assert ws.command("reset")["type"] == "error"  # anything but stop/pause: drive, needs the lease


def test_runs_of_others_are_invisible(server: Server, accounts: dict[str, Account], free_bench: None) -> None:
    student, student2 = accounts["student"], accounts["student2"]
    edu_run = server.start_run("relbot")
    server.stop_run()
    assert student.http.post("/api/lease/take").status_code == 200
    r = student.http.post("/api/runs", json={"build": "relbot"}, timeout=300)
    assert r.status_code == 201, r.text
    mine = r.json()
    assert mine["owner"] == "student"
    assert student.http.post("/api/runs/current/stop").status_code == 200
    # The owner and educators see it; another student gets exactly what a missing id gets.
    assert student.http.get(f"/api/runs/{mine['id']}").status_code == 200
    assert server.http.get(f"/api/runs/{mine['id']}").status_code == 200
    missing = student2.http.get("/api/runs/999999")
    for run_id in (mine["id"], edu_run["id"]):
        r = student2.http.get(f"/api/runs/{run_id}")
        assert r.status_code == 404 and r.json()["detail"] == f"no run {run_id}", r.text
        assert missing.status_code == 404
        logs = student2.http.get(f"/api/logs/runs/{run_id}")
        assert logs.status_code in (403, 404) and "relbot" not in logs.text
        assert student2.http.get(f"/api/logs/runs/{run_id}/files/output.txt").status_code in (403, 404)
    assert student.http.get(f"/api/runs/{edu_run['id']}").status_code == 404
    listed = {r["id"] for r in student2.http.get("/api/runs").json()}
    assert mine["id"] not in listed and edu_run["id"] not in listed
    assert {r["id"] for r in student.http.get("/api/runs").json()} == {mine["id"]} | (
        {r["id"] for r in student.http.get("/api/runs").json()} - {edu_run["id"]}
    )
    assert mine["id"] in {r["id"] for r in server.http.get("/api/runs").json()}


def _zip() -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("proj/CMakeLists.txt", "cmake_minimum_required(VERSION 3.16)\n")
        z.writestr("proj/src/main.cpp", "int main() { return 0; }\n")
    return buf.getvalue()


def test_observer_cannot_upload(server: Server, accounts: dict[str, Account]) -> None:
    before = server.http.get("/api/projects").json()
    obs = accounts["observer"]
    r = obs.http.post("/api/projects", files={"file": ("proj.zip", _zip(), "application/zip")})
    assert r.status_code == 403
    r = obs.http.post("/api/projects/from-template", json={"template": "base", "name": "x"})
    assert r.status_code == 403
    assert server.http.get("/api/projects").json() == before  # nothing created


def test_one_time_password_must_be_changed(server: Server) -> None:
    r = server.http.post("/api/users", json={"username": "newbie", "role": "student"})
    assert r.status_code == 201
    secret = r.json()["password"]
    http = login_client(server.url, "newbie", secret)
    assert http.get("/api/me").json()["must_change"]
    assert http.get("/api/bench").status_code == 403
    assert http.post("/api/auth/password", json={"current": secret, "new": "short"}).status_code == 422
    assert (
        http.post("/api/auth/password", json={"current": "wrong-one", "new": "a good new password"}).status_code == 401
    )
    assert http.post("/api/auth/password", json={"current": secret, "new": "a good new password"}).status_code == 204
    http.headers["X-CSRF-Token"] = http.cookies.get("xrf_csrf")
    assert http.get("/api/bench").status_code == 200
    assert not http.get("/api/me").json()["must_change"]
    with pytest.raises(AssertionError):
        login_client(server.url, "newbie", secret)  # the one-time password is gone
    http.close()


def test_disabled_account_is_locked_out_at_once(server: Server) -> None:
    acc = make_account(server, "leaver", "student")
    with acc.ws() as ws:
        ws.wait_type("state")
        assert server.http.patch(f"/api/users/{acc.id}", json={"disabled": True}).status_code == 200
        assert acc.http.get("/api/me").status_code == 401
        with pytest.raises(ConnectionClosed) as closed:  # its open WebSocket is closed at once
            ws.wait_type("never")
        assert closed.value.rcvd.code == 1008 and closed.value.rcvd.reason == "session ended"
    with pytest.raises(AssertionError):
        login_client(server.url, "leaver", acc.password)
    assert server.http.patch(f"/api/users/{acc.id}", json={"disabled": False}).status_code == 200
    login_client(server.url, "leaver", acc.password).close()


def test_educator_cannot_lock_themselves_out(server: Server) -> None:
    me = server.http.get("/api/me").json()
    assert server.http.patch(f"/api/users/{me['id']}", json={"disabled": True}).status_code == 409
    assert server.http.patch(f"/api/users/{me['id']}", json={"role": "student"}).status_code == 409


def test_api_token_for_the_cli(server: Server, accounts: dict[str, Account]) -> None:
    acc = make_account(server, "cliuser", "student")
    with anon(server) as c:
        r = c.post("/api/auth/token", json={"username": "cliuser", "password": acc.password})
        assert r.status_code == 200
        token = r.json()["token"]
    with httpx.Client(base_url=server.url, headers={"Authorization": f"Bearer {token}"}, timeout=30) as cli:
        assert cli.get("/api/me").json()["username"] == "cliuser"
        # No cookie, so no CSRF token needed: a bearer token is not sent by browsers on their own.
        assert cli.post("/api/lease/queue").status_code == 200
        assert cli.post("/api/lease/leave").status_code == 200
        assert cli.get("/api/users").status_code == 403  # still a student
        # A password reset by an educator ends the token.
        assert server.http.post(f"/api/users/{acc.id}/reset").status_code == 200
        assert cli.get("/api/me").status_code == 401


def test_class_list_import(server: Server) -> None:
    bad = "username,full name,role\ns100,Ann One,student\ns101,Bob Two,teacher\ns100,Ann Again,student\n"
    r = server.http.post("/api/users/import", json={"csv": bad})
    assert r.status_code == 422 and "line 3" in r.json()["detail"] and "line 4" in r.json()["detail"]
    assert not {"s100", "s101"} & _users(server)  # all or nothing
    good = "username,full name,role,email\ns100,Ann One,student,ann@example.edu\ns101,Bob Two,observer\n"
    r = server.http.post("/api/users/import", json={"csv": good})
    assert r.status_code == 201, r.text
    created = {c["user"]["username"]: c for c in r.json()["created"]}
    assert set(created) == {"s100", "s101"} and created["s101"]["user"]["role"] == "observer"
    http = login_client(server.url, "s100", created["s100"]["password"])
    assert http.get("/api/me").json()["must_change"]
    http.close()


def test_audit_trail(server: Server, accounts: dict[str, Account]) -> None:
    rows = server.http.get("/api/audit", params={"action": "user"}).json()
    assert any(
        r["action"] == "user.create" and r["detail"]["user"] == "student" and r["username"] == "admin" for r in rows
    )
    logins = server.http.get("/api/audit", params={"action": "auth.login", "username": "student"}).json()
    assert logins and all(r["username"] == "student" for r in logins)
    assert server.http.get("/api/audit", params={"action": "auth.failed"}).json()
    since = time.time() + 3600
    assert server.http.get("/api/audit", params={"since": since}).json() == []
    csv = server.http.get("/api/audit.csv", params={"action": "user"})
    assert csv.status_code == 200 and csv.headers["content-type"].startswith("text/csv")
    assert csv.text.splitlines()[0].startswith("id,time_utc,username,role,action")
    assert accounts["student"].http.get("/api/audit").status_code == 403
    assert accounts["observer"].http.get("/api/audit.csv").status_code == 403


def test_commands_and_runs_are_audited(server: Server, accounts: dict[str, Account], free_bench: None) -> None:
    run = server.start_run("relbot")
    with server.ws() as ws:
        ws.command("initialise")
    server.stop_run()
    rows = server.http.get("/api/audit", params={"username": "admin", "limit": 50}).json()
    actions = [r["action"] for r in rows]
    assert "command" in actions and "run.start" in actions and "run.stop" in actions
    start = next(r for r in rows if r["action"] == "run.start")
    assert start["detail"]["run"] == run["id"]
    assert next(r for r in rows if r["action"] == "command")["detail"]["cmd"] == "initialise"


# ---- brute force ------------------------------------------------------------------------------------


def test_login_rate_limit_per_account_and_per_address(tmp_path) -> None:
    s = start_server(tmp_path, shared_builds_root(), login_lock_s=2.0, login_max_failures_address=12)
    try:
        pw = s.create_user("target", "student")
        with anon(s) as c:
            for _ in range(5):
                assert (
                    c.post("/api/auth/login", json={"username": "target", "password": "guess-guess"}).status_code == 401
                )
            r = c.post("/api/auth/login", json={"username": "target", "password": pw})
            assert r.status_code == 429 and int(r.headers["Retry-After"]) >= 1  # even the right password
            assert c.post("/api/auth/token", json={"username": "target", "password": pw}).status_code == 429
            time.sleep(2.2)  # the point: the first lock (2 s) runs out
            # Backoff: the next lock of the same account (no success in between) is twice as long.
            for _ in range(5):
                assert (
                    c.post("/api/auth/login", json={"username": "target", "password": "guess-again"}).status_code == 401
                )
            time.sleep(2.2)  # the point: as long as the first lock, shorter than the second
            assert c.post("/api/auth/login", json={"username": "target", "password": pw}).status_code == 429
            time.sleep(2.2)  # the point: now the doubled lock has run out
            assert c.post("/api/auth/login", json={"username": "target", "password": pw}).status_code == 200
            # Per address: many different made-up accounts from one address lock the address.
            codes = [
                c.post("/api/auth/login", json={"username": f"guess{i}", "password": "guess-guess"}).status_code
                for i in range(4)
            ]
            assert codes == [401, 401, 429, 429]  # 10 failures above + 2 = the address's 12
            r = c.post("/api/auth/login", json={"username": "admin", "password": ADMIN_PASSWORD})
            assert r.status_code == 429
        failed = s.http.get("/api/audit", params={"action": "auth"}).json()
        assert any(r["action"] == "auth.locked" for r in failed)
    finally:
        stop_server(s)
