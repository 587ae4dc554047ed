"""A room and 5 appliances over a real mosquitto (TLS, the room's own CA): enrolment with `xrf room
join`, stop-all reaching every loop, messages, the class list (an account disabled in the room is
refused on a bench), single sign-on, a bench cut off and healed, the broker killed and restarted,
and the grid in a real chromium. Each appliance is a host of its own (a network namespace) where
the test runs as root; otherwise all share loopback on separate ports (printed: which mode ran)."""

from __future__ import annotations

import time
from collections.abc import Iterator

import httpx
import pytest

from xrf_testing.harness import CHROMIUM_ARGS, login_client, wait_for
from xrf_testing.room_support import (
    TEACHER,
    TEACHER_PW,
    Lab,
    Recorder,
    enrol_fake,
    enrol_request,
    room_endpoint,
    room_lab,
)
from xrflab.room import topics

N = 5


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Lab]:
    with room_lab(tmp_path_factory.mktemp("room"), N) as lab:
        yield lab


def test_enrolment_brings_every_bench_online(lab: Lab) -> None:
    wait_for(lambda: lab.online() == {f"b{i}" for i in range(1, N + 1)}, 20, "5 benches online")
    v = lab.views()["b1"]
    assert v["url"] == lab.benches[0].url and v["state"] == "NO RUN"
    # a code works once; a wrong one is refused
    code = lab.room.http.post("/api/room/join-codes").json()["code"]
    anon = httpx.Client(base_url=lab.room.url, timeout=10)
    assert anon.post("/api/room/enrol", json=enrol_request(code, "b9")).status_code == 200
    assert anon.post("/api/room/enrol", json=enrol_request(code, "b9")).status_code == 403
    assert anon.post("/api/room/enrol", json=enrol_request("nope", "b8")).status_code == 403
    # a bench's address must be a dashboard's, its key a key
    code = lab.room.http.post("/api/room/join-codes").json()["code"]
    assert anon.post("/api/room/enrol", json=enrol_request(code, "b8", "file:///etc/passwd")).status_code == 422
    assert anon.post("/api/room/enrol", json={**enrol_request(code, "b8"), "bench_key": "not-a-key"}).status_code == 422
    assert anon.post("/api/room/enrol", json=enrol_request(code, "b8")).status_code == 200  # the code still works
    # everything else of the room needs an educator's login
    assert anon.get("/api/room/benches").status_code == 401
    assert anon.post("/api/room/stop", json={}).status_code == 401
    anon.close()


def test_stop_all_reaches_every_loop(lab: Lab) -> None:
    for s in lab.benches:
        s.start_run("relbot")
        with s.ws() as ws:
            assert ws.command("initialise")["accepted"]
            ws.wait_state("INITIALISED", 15)
            assert ws.command("start")["accepted"]
            ws.wait_state("RUN", 15)
    wait_for(
        lambda: all(b["state"] == "RUN" for n, b in lab.views().items() if n not in ("b8", "b9")),
        10,
        "all RUN in the room",
    )
    sent = lab.teacher.post("/api/room/stop", json={}).json()
    replies = wait_for(
        lambda: (r := lab.room.http.get(f"/api/room/commands/{sent['id']}").json()["replies"]) and len(r) >= N and r,
        10,
        "5 replies",
    )
    assert {r["bench"] for r in replies} == {f"b{i}" for i in range(1, N + 1)}
    assert all("t_loop" in r for r in replies), replies
    lat = sorted(r["t_loop"] - r["t_sent"] for r in replies)
    print(f"stop-all: loop accepted after {[round(x * 1000, 1) for x in lat]} ms")
    assert all(r["accepted"] for r in replies)
    assert lat[-1] < 1.0  # 200 ms p99 is the LAN figure (bench/room); a loaded CI machine gets slack
    wait_for(
        lambda: all(b["state"] == "STOPPED" for n, b in lab.views().items() if n not in ("b8", "b9")), 10, "STOPPED"
    )
    for s in lab.benches:
        s.stop_run()  # end the runs: the loops' processes exit


def test_message_reaches_the_dashboards(lab: Lab) -> None:
    with lab.benches[1].ws() as ws:
        lab.teacher.post("/api/room/message", json={"text": "tea break in 5 minutes"})
        m = ws.wait_type("alarm", 5, kind="room")
        assert "tea break" in m["message"] and TEACHER in m["message"]


def test_class_list_disable_takes_effect_on_a_bench(lab: Lab) -> None:
    pw = "student-one-pw-123"

    def version() -> int:
        return int(lab.views()["b3"]["accounts_version"] or 0)

    before = version()
    r = lab.teacher.post("/api/users", json={"username": "s1", "role": "student", "password": pw, "must_change": False})
    assert r.status_code == 201, r.text
    uid = r.json()["user"]["id"]
    bench = lab.benches[2]
    # The bench says (its status) when it has applied the new class list; a login tried before
    # that fails, and five failures lock the account for this client a minute (the login guard):
    # polling the login itself locked the test out on a CI host (CI: not accepted within 30 s).
    wait_for(lambda: version() > before, 30, "the new class list applied on b3")
    student = login_client(bench.url, "s1", pw)
    assert student.get("/api/me").json()["username"] == "s1"
    t0 = time.monotonic()
    assert lab.teacher.patch(f"/api/users/{uid}", json={"disabled": True}).status_code == 200
    wait_for(lambda: student.get("/api/me").status_code == 401, 5, "session ended on the bench")
    assert time.monotonic() - t0 < 5
    with pytest.raises(AssertionError):
        login_client(bench.url, "s1", pw)
    student.close()
    # the bench's own accounts are its own: the room's admin did not replace the bench's admin
    assert bench.http.get("/api/me").status_code == 200


def test_single_sign_on(lab: Lab) -> None:
    url = lab.teacher.post("/api/room/benches/b2/sso").json()["url"]
    assert url.startswith(lab.benches[1].url + "/room/sso?token=")
    c = httpx.Client(timeout=10)
    r = c.get(url)
    assert r.status_code == 303 and "xrf_session" in r.cookies
    c.cookies = r.cookies
    me = c.get(lab.benches[1].url + "/api/me")
    assert me.json()["username"] == TEACHER and me.json()["role"] == "educator"
    assert c.get(url).status_code == 403  # used once
    token = url.split("token=")[1]
    assert c.get(lab.benches[2].url + "/room/sso", params={"token": token}).status_code == 403  # another bench's
    assert c.get(lab.benches[1].url + "/room/sso", params={"token": token[:-2] + "xx"}).status_code == 403
    # the room's `admin` is not the bench's `admin`: no sign-on into a bench's own account
    url2 = lab.room.http.post("/api/room/benches/b2/sso").json()["url"]
    assert c.get(url2).status_code == 403
    c.close()


def test_bench_cut_off_and_healed(lab: Lab) -> None:
    i, s = 4, lab.benches[3]
    wait_for(lambda: "b4" in lab.online(), 10, "b4 online")
    t0 = time.monotonic()
    lab.topo.cut(i, s)
    try:
        wait_for(lambda: "b4" not in lab.online(), 6, "b4 offline")
        took = time.monotonic() - t0
        print(f"cut off ({lab.topo.mode}): offline in the room after {took:.1f} s")
        assert took < 5.5
        assert {f"b{j}" for j in (1, 2, 3, 5)} <= lab.online()
    finally:
        lab.topo.heal(i, s)
    wait_for(lambda: "b4" in lab.online(), 20, "b4 back online")


def test_broker_killed_and_restarted(lab: Lab) -> None:
    wait_for(lambda: len(lab.online() & {f"b{i}" for i in range(1, N + 1)}) == N, 20, "all online")
    lab.broker.kill()
    wait_for(lambda: not lab.room.http.get("/api/room/benches").json()["connected"], 10, "room sees the broker gone")
    # benches run on alone: a run starts and ends on b1 with no broker
    b1 = lab.benches[0]
    b1.start_run("relbot")
    b1.stop_run()
    lab.broker.start()
    wait_for(lambda: lab.room.http.get("/api/room/benches").json()["connected"], 15, "room reconnected")
    wait_for(lambda: len(lab.online() & {f"b{i}" for i in range(1, N + 1)}) == N, 20, "all back online")
    # the events b1 queued during the outage reached the room
    wait_for(
        lambda: any(e["kind"] == "run_ended" and e["t"] > 0 for e in lab.views()["b1"]["events"]),
        10,
        "b1's queued run_ended",
    )


def test_grid_in_chromium(lab: Lab, chromium_path: str) -> None:
    """30 benches fit on a 1366x768 laptop screen; alarms first; a bench that stops talking is shown
    offline within 5 s."""
    from playwright.sync_api import sync_playwright

    files = lab.broker.files
    for k in range(25):  # the room hears enrolled benches only
        enrol_fake(lab.room, f"z{k:02d}")
    fake = Recorder(room_endpoint(files), "fakes")  # the room's own credentials: may write any bench's topics
    assert fake.wait_connected()
    boot = int(time.time() * 1000)

    def publish_fakes(seq: int, alarm_on: str = "") -> None:
        for k in range(25):
            name = f"z{k:02d}"
            fake.publish(topics.bench(name, "online"), {"online": True, "conn": [boot, 1]}, retain=True)
            fake.publish(
                topics.bench(name, "status"),
                {
                    "boot": boot,
                    "seq": seq,
                    "state": "RUN",
                    "holder": f"st{k}",
                    "alarms": [{"kind": "crash", "message": "segfault"}] if name == alarm_on else [],
                },
                retain=True,
            )

    import threading

    beating = threading.Event()
    beating.set()

    def heartbeat() -> None:  # as live benches do: a status every second
        seq = 1
        while beating.is_set():
            publish_fakes(seq, alarm_on="z17")
            seq += 1
            time.sleep(1.0)

    beater = threading.Thread(target=heartbeat, daemon=True)
    beater.start()
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium_path, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1366, "height": 768})
            page.goto(lab.room.url + "/")
            page.fill("#login-user", TEACHER)
            page.fill("#login-pass", TEACHER_PW)
            page.click("#login-submit")
            page.wait_for_function("document.querySelectorAll('.tile').length >= 30", timeout=15000)
            boxes = page.eval_on_selector_all(
                ".tile",
                "els => els.map(e => { const r = e.getBoundingClientRect(); "
                "return [r.left, r.top, r.right, r.bottom]; })",
            )
            assert all(r <= 1366 and b <= 768 for _, _, r, b in boxes), boxes
            # alarms first: every tile with an alarm comes before every tile without one
            flags = page.eval_on_selector_all(
                ".tile", "els => els.map(e => [e.dataset.bench, e.classList.contains('has-alarm')])"
            )
            alarmed = [f for _, f in flags]
            assert alarmed == sorted(alarmed, reverse=True) and dict(flags)["z17"], flags
            # a stale status (older seq) never overwrites the newer one the grid shows
            fake.publish(topics.bench("z03", "status"), {"boot": boot, "seq": 0, "state": "PAUSED"}, retain=True)
            time.sleep(0.5)  # the point: within this window the grid must NOT change
            assert page.eval_on_selector("[data-bench=z03] .state", "e => e.textContent") == "RUN"
            fake.publish(
                topics.bench("z03", "status"), {"boot": boot - 1, "seq": 10**6, "state": "PAUSED"}, retain=True
            )
            time.sleep(0.5)  # the point: within this window the grid must NOT change
            assert page.eval_on_selector("[data-bench=z03] .state", "e => e.textContent") == "RUN"
            # the fakes fall silent: offline within 5 s; the real benches stay online
            beating.clear()
            beater.join()
            t0 = time.monotonic()
            page.wait_for_function("document.querySelectorAll('.tile.offline').length >= 25", timeout=6000)
            assert time.monotonic() - t0 < 5.5
            assert page.eval_on_selector("[data-bench=b1]", "e => e.classList.contains('offline')") is False
            # STOP ALL from the page reaches the benches (their replies come back to the room)
            page.click("#room-stop-all")
            page.wait_for_function("document.getElementById('room-note').textContent.startsWith('stop sent')")
            browser.close()
    finally:
        beating.clear()
        for k in range(25):  # leave no retained fakes behind
            fake.publish(topics.bench(f"z{k:02d}", "status"), b"", retain=True)
            last = fake.publish(topics.bench(f"z{k:02d}", "online"), b"", retain=True)
        fake.wait_ack(last)  # QoS 1 in order: the broker has every clear before the connection goes
        fake.close()
