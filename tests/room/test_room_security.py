"""The room against a bench that has been taken over (issue 26, holes 8 and 9): a student whose
controller read everything the bench keeps -- its enrolment file, its broker login, its keys --
and uses it from elsewhere. Real mosquitto (TLS, the room's CA), a real room, real appliances
enrolled with `xrf room join`.

- forged statuses (a boot far ahead, a foreign url) neither displace the real bench on the room
  page for good nor redirect "open bench";
- malformed, oversized and wrong-typed payloads on every topic, both directions, are dropped and
  both sides keep working;
- nothing a bench holds mints a sign-on token any bench accepts, for any user;
- the bench's secrets are the appliance's alone (0600/0700, its user), the room keeps none of a
  bench's, and an enrolment from before signed tokens says "re-enrol" on both sides.

The attacker's tokens are made here with `cryptography` and `hmac` directly (not with
xrflab.room.sso), so that the tests say the same against any version of the room's code."""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import os
import secrets
import stat
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from xrf_testing.harness import login_client, shared_builds_root, start_server, stop_server, wait_for
from xrf_testing.room_support import (
    TEACHER,
    Lab,
    Recorder,
    as_bench,
    broker_files,
    held,
    join,
    room_endpoint,
    room_lab,
    sent,
    start_broker,
    start_room,
)
from xrflab.room import topics

N = 2
EVIL = "https://evil.example"


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Lab]:
    with room_lab(tmp_path_factory.mktemp("room-sec"), N) as lab:
        wait_for(lambda: {"b1", "b2"} <= lab.online(), 30, "b1 and b2 online")
        yield lab


def b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode()


def loads(payload: bytes) -> dict[str, Any]:
    """A JSON object, or {} for anything else (the garbage the tests send passes by too)."""
    try:
        m = json.loads(payload)
    except (ValueError, RecursionError):
        return {}
    return m if isinstance(m, dict) else {}


def strings(value: Any) -> Iterator[str]:
    if isinstance(value, str):
        yield value
    elif isinstance(value, dict):
        for v in value.values():
            yield from strings(v)
    elif isinstance(value, list):
        for v in value:
            yield from strings(v)


def test_forged_status_neither_displaces_the_bench_nor_redirects_open(lab: Lab) -> None:
    b1 = lab.benches[0]
    attacker = as_bench(lab, 0)
    now_ms = time.time_ns() // 1_000_000
    try:
        # the issue's: a boot no integer holds (9e18 is a float in JSON), then one centuries ahead,
        # then a plausible one a minute ahead of everything the bench says (newer by (boot, seq))
        for boot, seq in ((9e18, 1), (9 * 10**15, 1), (now_ms + 60_000, 10**12)):
            status = {"boot": boot, "seq": seq, "t": time.time(), "url": EVIL, "state": "HACKED", "holder": "mallory"}
            sent(attacker, topics.bench("b1", "status"), status, retain=True)
        # the two impossible boots are dropped (and counted) before anything is asked of the room
        wait_for(lambda: lab.views()["b1"]["dropped"] >= 2, 5, "the impossible boots dropped")
        # "open bench" signs the educator on at the address recorded at enrolment, whatever b1 says
        for _ in range(3):
            url = lab.teacher.post("/api/room/benches/b1/sso").json()["url"]
            assert url.startswith(b1.url + "/room/sso?token="), url
            assert lab.views()["b1"]["url"] == b1.url
            time.sleep(0.5)
        # the forged "newer" status is shown at most a few seconds: the live bench is back, and stays
        wait_for(lambda: lab.views()["b1"]["state"] != "HACKED", 6, "the real b1 on its tile again")
        for _ in range(8):
            v = lab.views()["b1"]
            assert v["state"] != "HACKED" and v["holder"] != "mallory" and v["online"], v
            time.sleep(0.5)
        assert lab.views()["b1"]["dropped"] >= 2  # the two impossible boots, dropped and counted
        # a forged last will ("offline", of a connection far newer than the live one): the live
        # bench's next status shows it online again
        sent(attacker, topics.bench("b1", "online"), {"online": False, "conn": [9 * 10**15, 1]}, retain=True)
        time.sleep(0.2)  # the room's thread sees the will (nothing in its view says so when it is right)
        wait_for(lambda: lab.views()["b1"]["online"], 4, "b1 online again after a forged will")
        # and the link still works: the educator lands on the real bench, as themselves
        c = httpx.Client(timeout=10)
        r = c.get(lab.teacher.post("/api/room/benches/b1/sso").json()["url"])
        assert r.status_code == 303 and "xrf_session" in r.cookies
        c.cookies = r.cookies
        assert c.get(b1.url + "/api/me").json()["username"] == TEACHER
        c.close()
    finally:
        attacker.close()


def test_only_an_educator_moves_a_bench(lab: Lab) -> None:
    """The address "open bench" uses changes with an educator's PATCH (audited), nothing else."""
    real = lab.benches[1].url
    anon = httpx.Client(base_url=lab.room.url, timeout=10)
    assert anon.patch("/api/room/benches/b2", json={"url": EVIL}).status_code in (401, 403)
    anon.close()
    assert lab.teacher.patch("/api/room/benches/b2", json={"url": "javascript:alert(1)"}).status_code == 422
    assert lab.teacher.patch("/api/room/benches/b2", json={"url": "http://10.9.9.9:8000"}).status_code == 200
    try:
        assert lab.teacher.post("/api/room/benches/b2/sso").json()["url"].startswith("http://10.9.9.9:8000/room/sso?")
        audit = lab.room.http.get("/api/audit", params={"action": "room.bench_address"}).json()
        assert "10.9.9.9" in json.dumps(audit)
    finally:
        assert lab.teacher.patch("/api/room/benches/b2", json={"url": real}).status_code == 200
    assert lab.teacher.post("/api/room/benches/b2/sso").json()["url"].startswith(real + "/room/sso?")


# Payloads no topic accepts: not JSON, not UTF-8, not an object, nested without end, wrong types,
# impossible numbers.
GARBAGE: list[bytes] = [
    b"not json",
    b"\xff\xfe\x00\x01",
    b"[]",
    b"null",
    b"42",
    b"[" * 50_000 + b"]" * 50_000,
    b'{"boot": NaN, "seq": 1}',
    json.dumps({"boot": "1", "seq": "2", "online": "yes", "conn": "zz", "kind": 7, "id": 7}).encode(),
    json.dumps({"boot": -1, "seq": 1.5, "online": 1, "conn": [1, 2, 3], "t": -5, "kind": "alarm", "id": "ZZ"}).encode(),
]


def over_bounds(now_ms: int) -> dict[str, list[Any]]:
    """Well-typed, newer than anything the bench said, but over a bound: strings, lists, sizes,
    numbers, kinds."""
    new = {"boot": now_ms + 1000, "seq": 10**9, "t": time.time()}
    return {
        "status": [
            {**new, "state": "Y" * 40},
            {**new, "state": "HACKED", "alarms": [{"kind": "crash", "message": "m"}] * 50},
            {**new, "state": "HACKED", "message": "X" * (100 << 10)},
            {**new, "state": "HACKED", "cycles": 2**70},
        ],
        "event": [
            {**new, "kind": "run_started", "run_id": 1, "owner": "o" * 100},
            {**new, "kind": "no_such_kind"},
            {**new, "kind": "alarm", "alarm": "crash", "message": "m" * 301},
        ],
        "reply": [{"id": "deadbeef", "cmd": "stop", "ok": True, "t_recv": 1e300}],
    }


def test_malformed_payloads_are_dropped_both_ways(lab: Lab) -> None:
    b1 = lab.benches[0]
    wait_for(lambda: lab.views()["b1"]["online"], 10, "b1 online")
    before = lab.views()["b1"].get("dropped", 0)
    attacker = as_bench(lab, 0)
    room = Recorder(room_endpoint(lab.broker.files), "room-probe", [topics.bench("b1", "reply")])
    assert room.wait_connected()
    n = 0
    try:
        # bench -> room: every leaf it may write, and one the room does not know
        for leaf in ("online", "status", "event", "reply", "nonsense"):
            for payload in GARBAGE:
                sent(attacker, topics.bench("b1", leaf), payload)
                n += 1
        for leaf, bodies in over_bounds(time.time_ns() // 1_000_000).items():
            for body in bodies:
                sent(attacker, topics.bench("b1", leaf), body)
                n += 1
        # a well-formed answer to a command the room never sent is not kept either
        sent(attacker, topics.bench("b1", "reply"), {"id": "deadbeef", "cmd": "stop", "ok": True, "t_recv": 1.0})
        n += 1
        time.sleep(1.0)  # handed from paho's thread to the room's loop
        v = lab.views()["b1"]
        assert v["online"] and v["state"] not in ("HACKED", "Y" * 40) and len(json.dumps(v)) < 20_000, v
        assert not any(e["kind"] in ("no_such_kind",) or e.get("owner") == "o" * 100 for e in v["events"]), v
        assert lab.room.http.get("/api/room/commands/deadbeef").json()["replies"] == []
        wait_for(lambda: lab.views()["b1"]["dropped"] >= before + n, 10, f"{n} payloads dropped")

        # room -> bench (only the room may write there: its login): commands, class list, assignment
        now = time.time()
        for payload in GARBAGE:
            room.publish(topics.cmd("b1"), payload)
        room.publish(topics.cmd("b1"), {"id": "abc1", "cmd": "reboot", "t": now})  # no such command
        room.publish(topics.cmd("b1"), {"id": "abc2", "cmd": "message", "text": 5, "t": now})
        room.publish(topics.cmd("b1"), {"id": "abc3", "cmd": "message", "text": "x" * 501, "t": now})
        room.publish(topics.cmd("b1"), {"id": "../x", "cmd": "stop", "t": now})  # no id to answer
        for payload in [*GARBAGE[:8], json.dumps({"version": 1e300, "users": []}).encode()]:
            room.publish(topics.ACCOUNTS, payload, retain=True)
        room.publish(topics.ACCOUNTS, {"version": 2**60, "users": []}, retain=True)  # past any version
        room.publish(topics.ACCOUNTS, {"version": 10**15, "users": "everyone"}, retain=True)
        for payload in [*GARBAGE[:8], {"id": "a1", "sha256": "x", "path": "/etc/passwd", "inline": "%%"}]:
            room.publish(topics.assignment("a1"), payload, retain=True)
        # an unknown or malformed command with an id is answered "not understood"; the others are not
        for cid in ("abc1", "abc2", "abc3"):
            _, raw, _ = room.wait_message(lambda t, p, cid=cid: loads(p).get("id") == cid, 10)
            reply = json.loads(raw)
            assert reply["ok"] is False and reply["error"], reply
        time.sleep(0.5)  # the point: listen a while for what must NOT be answered
        assert not room.received(lambda t, p: b"../x" in p)

        # both sides work on: the room's stop reaches b1's loop and comes back, the class list too
        cmd = lab.teacher.post("/api/room/stop", json={"bench": "b1"}).json()
        wait_for(
            lambda: [r for r in lab.room.http.get(f"/api/room/commands/{cmd['id']}").json()["replies"] if r["ok"]],
            10,
            "b1 answers stop",
        )
        pw = "student-nine-pw-123"
        r = lab.teacher.post(
            "/api/users", json={"username": "s9", "role": "student", "password": pw, "must_change": False}
        )
        assert r.status_code == 201, r.text

        def s9_accepted() -> httpx.Client | None:
            try:
                return login_client(b1.url, "s9", pw)
            except AssertionError:
                time.sleep(1.5)  # spaced: 5 failed logins lock the account
                return None

        wait_for(s9_accepted, 10, "the room's new student accepted on b1").close()
        assert b1.http.get("/api/health").status_code == 200
        assert lab.views()["b1"]["online"]
    finally:
        room.wait_ack(room.publish(topics.assignment("a1"), b"", retain=True))  # cleared before we go
        room.close()
        attacker.close()


def test_nothing_a_bench_holds_mints_a_sign_on(lab: Lab) -> None:
    """Hole 8: with the enrolment file of a bench (every secret in it, every key), a token for an
    educator of the room -- or anyone -- is refused by that bench and by every other."""
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    stolen = held(lab, 0)
    secrets_held = {s for s in strings(stolen) if len(s) >= 16}
    assert secrets_held, stolen
    tokens: list[str] = []
    for bench in ("b1", "b2"):
        for user in (TEACHER, "admin"):
            claims = {
                "bench": bench,
                "user": user,
                "exp": time.time() + 50,
                "use": "sso",
                "nonce": secrets.token_hex(8),
            }
            body = b64(json.dumps(claims, separators=(",", ":")).encode())
            # the old scheme: HMAC-SHA256 with any secret the bench keeps
            for key in secrets_held:
                tokens.append(f"{body}.{b64(hmac.new(key.encode(), body.encode(), hashlib.sha256).digest())}")
            # Ed25519 with any 32 bytes the bench keeps as a key (its own private key among them)
            for key in secrets_held:
                try:
                    raw = base64.urlsafe_b64decode(key + "=" * (-len(key) % 4))
                except ValueError:
                    continue
                if len(raw) == 32:
                    tokens.append(f"{body}.{b64(Ed25519PrivateKey.from_private_bytes(raw).sign(body.encode()))}")
    assert len(tokens) > 8
    c = httpx.Client(timeout=10)
    for i, bench in enumerate(lab.benches):
        for token in tokens:
            r = c.get(bench.url + "/room/sso", params={"token": token})
            assert r.status_code == 403 and "xrf_session" not in r.cookies, (f"b{i + 1}", r.status_code, r.text)
    # the room's own link still signs the educator on
    r = c.get(lab.teacher.post("/api/room/benches/b1/sso").json()["url"])
    assert r.status_code == 303 and "xrf_session" in r.cookies
    c.close()


def test_a_benchs_key_serves_that_bench_alone(lab: Lab) -> None:
    """What b1's key does sign (fetching an assignment, uploading its runs) is honoured for b1 only."""
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    raw = base64.urlsafe_b64decode(held(lab, 0)["bench_key"] + "=")
    key = Ed25519PrivateKey.from_private_bytes(raw)

    def token(bench: str, use: str, subject: str) -> str:
        claims = {"bench": bench, "user": subject, "exp": time.time() + 50, "use": use, "nonce": secrets.token_hex(8)}
        body = b64(json.dumps(claims).encode())
        return f"{body}.{b64(key.sign(body.encode()))}"

    anon = httpx.Client(base_url=lab.room.url, timeout=10)
    path = "/api/room/assignments/a0-none/archive"
    # as b1: the token is good (the assignment does not exist: 404, not 403)
    assert anon.get(path, params={"bench": "b1", "token": token("b1", "assignment", "a0-none")}).status_code == 404
    # as b2, or for another use, or signed with anything else: refused
    assert anon.get(path, params={"bench": "b2", "token": token("b2", "assignment", "a0-none")}).status_code == 403
    assert anon.get(path, params={"bench": "b1", "token": token("b1", "sso", "a0-none")}).status_code == 403
    assert anon.get(path, params={"bench": "b1", "token": token("b1", "collect", "a0-none")}).status_code == 403
    anon.close()


def _mode(p: Path) -> int:
    return stat.S_IMODE(p.stat().st_mode)


def test_bench_secrets_are_the_appliances_alone(lab: Lab, tmp_path: Path) -> None:
    if os.geteuid() == 0:
        # `xrf room join` run as root for an appliance that runs as another user: the file is that user's
        other = tmp_path / "other"
        other.mkdir()
        os.chown(other, 65534, 65534)
        res = join(lab.room, "b7", other, "http://127.0.0.1:9", lab.room_url)
        assert res.returncode == 0, res.stdout + res.stderr
        f = other / "room" / "enrolment.json"
        assert (f.stat().st_uid, f.stat().st_gid, _mode(f)) == (65534, 65534, 0o600)
        assert ((other / "room").stat().st_uid, _mode(other / "room")) == (65534, 0o700)
    for s in lab.benches:
        folder, f = s.data_dir / "room", s.data_dir / "room" / "enrolment.json"
        assert (_mode(folder), _mode(f)) == (0o700, 0o600)
        assert f.stat().st_uid == folder.stat().st_uid == s.data_dir.stat().st_uid
    # the room keeps its signing key private, and no secret of any bench (public keys only)
    rd = lab.room.data_dir
    assert _mode(rd / "signing.key") == 0o600 and _mode(rd / "benches.json") == 0o600
    enrolled = json.loads((rd / "benches.json").read_text())
    assert "sso_key" not in json.dumps(enrolled) and enrolled["b1"]["url"] == lab.benches[0].url


def test_enrolment_before_signed_tokens_says_re_enrol(tmp_path: Path) -> None:
    """An enrolment from before (an HMAC key shared by the room and the bench): the bench still
    reports and obeys through the broker, nobody honours the old key any more, and both the bench's
    /room/sso and the room's "open bench" say to enrol again. The room forgets the old key."""
    room_dir = tmp_path / "room"
    files = broker_files(room_dir / "broker")  # the room's own broker folder, as `xrf room` has it
    broker = start_broker(files)
    old_key = secrets.token_urlsafe(32)
    (room_dir / "benches.json").write_text(
        json.dumps({"b1": {"sso_key": old_key, "enrolled": time.time(), "address": "127.0.0.1"}})
    )
    pw = f"pw-b1-{secrets.token_hex(6)}"
    files.set_password("b1", pw)
    files.reload()
    data = tmp_path / "bench"
    (data / "room").mkdir(parents=True)
    os.chmod(data / "room", 0o700)
    old = {
        "name": "b1",
        "sso_key": old_key,
        "broker": {"host": "127.0.0.1", "port": files.port, "username": "b1", "password": pw},
    }
    fd = os.open(data / "room" / "enrolment.json", os.O_WRONLY | os.O_CREAT, 0o600)
    with os.fdopen(fd, "w") as f:
        json.dump(old, f)
    room = start_room(room_dir, files)
    server = start_server(data, shared_builds_root())
    try:
        # the bench reports through the broker as before
        wait_for(
            lambda: (b := room.http.get("/api/room/benches").json()["benches"]) and b[0]["online"] and b[0],
            20,
            "the old bench online in the room",
        )
        # the bench refuses tokens of the old key and says what to do
        claims = {"bench": "b1", "user": "admin", "exp": time.time() + 50, "nonce": secrets.token_hex(8)}
        body = b64(json.dumps(claims).encode())
        token = f"{body}.{b64(hmac.new(old_key.encode(), body.encode(), hashlib.sha256).digest())}"
        r = httpx.get(server.url + "/room/sso", params={"token": token}, timeout=10)
        assert r.status_code == 404 and "xrf room join" in r.text and "xrf_session" not in r.cookies
        # the room no longer keeps the old shared key, makes no link, and says what to do
        assert old_key not in (room_dir / "benches.json").read_text()
        r = room.http.post("/api/room/benches/b1/sso")
        assert r.status_code == 409 and "xrf room join" in r.json()["detail"]
        view = room.http.get("/api/room/benches").json()["benches"][0]
        assert view["enrolment"] == "outdated" and "xrf room join" in view["problem"]
        # and the room's commands still reach it
        cmd = room.http.post("/api/room/stop", json={"bench": "b1"}).json()
        wait_for(lambda: room.http.get(f"/api/room/commands/{cmd['id']}").json()["replies"], 10, "b1 answers")
    finally:
        stop_server(server)
        room.stop()
        broker.stop()
