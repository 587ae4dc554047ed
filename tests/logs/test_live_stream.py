"""The live rerun stream through the appliance (issue 4 item 5): the viewer's gRPC-web reads are
answered at the appliance's root, behind the login, from the Pi's LAN address; one rerun proxy
per run, on 127.0.0.1 only; only the run's owner and educators receive its data (anyone else
gets what no live run at all gives); a new run
ends the previous run's stream; closed viewers free their connection."""

from __future__ import annotations

import threading
import time
import urllib.parse
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from xrf_testing.grpcweb import GRPC_WEB, READ_MESSAGES, read_messages
from xrf_testing.harness import ADMIN_PASSWORD, ADMIN_USER, Server, free_port, login_client, stop_server
from xrf_testing.logs_support import PROBE, start, wait_for
from xrf_testing.net import established_to, lan_address, listening_addresses
from xrf_testing.rerun_stream import STORE_RECORDING, chunk_of
from xrflab.server.http.rerun import NO_LIVE_STREAM

SERVICE = "/rerun.sdk_comms.v1alpha1.MessageProxyService"


def children(pid: int) -> dict[int, list[str]]:
    """{pid: argv} of the processes whose parent is `pid`."""
    out = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            argv = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
            out[int(entry.name)] = [a.decode() for a in argv if a]
    return out


def live_proxies(server: Server) -> dict[int, int]:
    """{pid: port} of the appliance's rerun live proxies (rerun --serve-grpc children)."""
    found = {}
    for pid, argv in children(server.proc.pid).items():
        if "--serve-grpc" in argv:
            found[pid] = int(argv[argv.index("--port") + 1])
    return found


@pytest.fixture(scope="module")
def lan() -> Iterator[tuple[Server, str]]:
    """An appliance listening on every interface, and its URL by the LAN address."""
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        s = start(Path(d) / "data", host="0.0.0.0")
        port = s.url.rsplit(":", 1)[1]
        try:
            yield s, f"http://{lan_address()}:{port}"
        finally:
            stop_server(s)


def run_probe(server: Server, http: httpx.Client | None = None) -> int:
    http = http or server.http
    server.stop_run()
    r = http.post("/api/runs", json={"build": PROBE}, timeout=300)
    assert r.status_code == 201, r.text
    run_id = r.json()["id"]
    for cmd in ("initialise", "start"):
        r = http.post("/api/runs/current/command", json={"cmd": cmd})
        assert r.status_code == 200 and r.json()["accepted"], r.text
    # the run's live proxy starts beside the run (not on the event loop): wait until it is the current one
    wait_for(lambda: http.get("/api/logs/rerun").json()["live_run"] == run_id, timeout=20, what="the run's live proxy")
    return run_id


def test_live_stream_from_the_lan_address_through_the_login(lan) -> None:
    server, url = lan
    http = login_client(url, ADMIN_USER, ADMIN_PASSWORD)
    try:
        run_id = run_probe(server, http)
        info = http.get("/api/logs/rerun").json()
        # the URL names the host and port the browser used: the appliance's own origin
        assert info["live_url"] == f"rerun+{url}/proxy"
        assert info["live_allowed"] and info["live_running"] and info["live_recording"] == f"run-{run_id}"
        got = read_messages(http, READ_MESSAGES, until=lambda d: f"run-{run_id}".encode() in d and b"ratio" in d)
        assert got.status == 200 and got.headers["content-type"] == "application/grpc-web+proto"
        # the run's recording: its id and a logged variable of the probe (entity log/.../ratio)
        assert f"run-{run_id}".encode() in got.data and b"ratio" in got.data, got.data[:200]
        assert "access-control-allow-origin" not in got.headers  # same origin: no CORS granted
        # rerun's own servers: one live proxy for this run, on 127.0.0.1 only
        proxies = live_proxies(server)
        assert len(proxies) == 1
        (port,) = proxies.values()
        assert listening_addresses(port) == {"127.0.0.1"}
        if not url.startswith("http://127."):
            with pytest.raises(httpx.ConnectError):
                httpx.post(f"http://{lan_address()}:{port}{READ_MESSAGES}", headers=GRPC_WEB, content=b"\0" * 5)
    finally:
        http.close()


def test_the_live_stream_refuses_what_it_must(lan) -> None:
    server, url = lan
    run_probe(server)
    proxy_url = url + READ_MESSAGES
    body = b"\0\0\0\0\0"
    # no login
    assert httpx.post(proxy_url, headers={**GRPC_WEB, "Origin": url}, content=body).status_code == 401
    http = login_client(url, ADMIN_USER, ADMIN_PASSWORD)
    cookies = {"xrf_session": http.cookies.get("xrf_session")}
    try:
        # a cookie but a foreign page (Origin), or no Origin at all: cross-site, refused
        for origin in ({"Origin": "http://evil.example"}, {}):
            r = httpx.post(proxy_url, headers={**GRPC_WEB, **origin}, cookies=cookies, content=body)
            assert r.status_code == 403 and "cross-site" in r.json()["detail"], r.text
        # same origin, but a content type a form can send: this is what the CSRF token would stop
        r = httpx.post(proxy_url, headers={"Origin": url, "content-type": "text/plain"}, cookies=cookies, content=body)
        assert r.status_code == 403 and "gRPC-web" in r.json()["detail"], r.text
        # writing into a run's recording from a browser: refused with a gRPC status the viewer shows
        r = http.post(url + SERVICE + "/WriteMessages", headers=GRPC_WEB, content=body)
        assert r.status_code == 403 and r.headers["grpc-status"] == "7", r.headers
        assert "read-only" in r.headers["grpc-message"]
        # an oversized request: refused before it is forwarded
        r = http.post(proxy_url, headers=GRPC_WEB, content=b"\0" * (65 * 1024))
        assert r.status_code == 413 and r.headers["grpc-status"] == "8"
        # an API token (`xrf login`) needs no Origin: it is not a browser
        token = httpx.post(
            url + "/api/auth/token", json={"username": ADMIN_USER, "password": ADMIN_PASSWORD}, headers={"Origin": url}
        ).json()["token"]
        with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"}) as api:
            got = read_messages(api, READ_MESSAGES, until=lambda d: b"run-" in d)
            assert got.status == 200 and b"run-" in got.data
    finally:
        http.close()


def test_only_the_owner_and_educators_see_a_run_live(lan) -> None:
    server, url = lan
    pw_a = server.create_user("live_alice", "student")
    pw_b = server.create_user("live_bob", "student")
    alice = login_client(url, "live_alice", pw_a)
    bob = login_client(url, "live_bob", pw_b)
    try:
        server.stop_run()
        assert alice.post("/api/lease/take").status_code == 200
        run_id = run_probe(server, alice)
        mine = read_messages(alice, READ_MESSAGES, until=lambda d: f"run-{run_id}".encode() in d)
        assert mine.status == 200 and f"run-{run_id}".encode() in mine.data
        # Someone else's live run answers as no live run at all (server/security/ownership.py): not its id, not
        # its owner, and the stream a 404 NOT_FOUND word for word like the one before any run.
        info = bob.get("/api/logs/rerun").json()
        assert info["live_run"] is None and not info["live_allowed"] and info["live_url"] == ""
        assert info["live_recording"] == "" and "live_alice" not in info["live_reason"]
        assert info["live_reason"] == NO_LIVE_STREAM
        theirs = read_messages(bob, READ_MESSAGES)
        assert theirs.status == 404 and theirs.headers["grpc-status"] == "5" and not theirs.data
        assert urllib.parse.unquote(theirs.headers["grpc-message"]) == NO_LIVE_STREAM
        educator = read_messages(server.http, READ_MESSAGES, until=lambda d: f"run-{run_id}".encode() in d)
        assert educator.status == 200 and f"run-{run_id}".encode() in educator.data
        alice.post("/api/runs/current/stop", timeout=30)
        alice.post("/api/lease/release")
    finally:
        alice.close()
        bob.close()


def test_a_new_run_has_its_own_stream_and_ends_the_old_one(lan) -> None:
    server, url = lan
    http = login_client(url, ADMIN_USER, ADMIN_PASSWORD)
    try:
        first = run_probe(server, http)
        # a viewer of the first run stays connected while the second starts
        ended: dict[str, object] = {}

        def watch() -> None:
            ended["stream"] = read_messages(http, READ_MESSAGES, timeout=120, quiet=120)
            ended["at"] = time.monotonic()

        viewer = threading.Thread(target=watch)
        viewer.start()
        wait_for(lambda: http.get("/api/logs/rerun").json()["live_viewers"] >= 1, timeout=20, what="the viewer")
        old_proxies = live_proxies(server)  # started for that viewer
        assert old_proxies
        second = run_probe(server, http)
        viewer.join(30)
        assert not viewer.is_alive(), "the first run's stream did not end when the next run started"
        assert ended["stream"].ended_by == "server"  # type: ignore[union-attr]
        assert f"run-{first}".encode() in ended["stream"].data  # type: ignore[union-attr]
        # the first run's proxy is gone; the second has its own, which knows nothing of the first
        assert not set(old_proxies) & set(live_proxies(server))
        got = read_messages(http, READ_MESSAGES, until=lambda d: f"run-{second}".encode() in d and b"ratio" in d)
        assert f"run-{second}".encode() in got.data and f"run-{first}".encode() not in got.data
    finally:
        http.close()


def test_a_closed_viewer_frees_its_stream(lan) -> None:
    server, url = lan
    http = login_client(url, ADMIN_USER, ADMIN_PASSWORD)
    try:
        run_probe(server, http)
        before = http.get("/api/logs/rerun").json()["live_viewers"]
        for _ in range(3):
            got = read_messages(http, READ_MESSAGES, until=lambda d: b"run-" in d)
            assert got.status == 200
        # each stream was closed by the client mid-way: the appliance closes its upstream too
        wait_for(
            lambda: http.get("/api/logs/rerun").json()["live_viewers"] == before,
            timeout=10,
            what="closed viewers to be counted out",
        )
        (port,) = live_proxies(server).values()
        assert established_to(port) <= 1  # only the run's own recording stream
    finally:
        http.close()
        server.stop_run()


def test_a_connected_viewer_gets_one_message_per_view_and_new_samples(lan) -> None:
    """Issue 19 (a viewer 5-9 minutes behind): rerun's viewer ingests messages for at most 10 ms
    per frame, so the stream's message count, not its bytes, decides whether a slow browser keeps
    up. Each batch brings one message per view (a variable group's variables are the series of
    one entity), not one per variable; and a viewer already connected receives samples the loop
    logged after it connected, without more data having to push them out."""
    server, url = lan
    http = login_client(url, ADMIN_USER, ADMIN_PASSWORD)
    try:
        run_id = run_probe(server, http)
        connected_ns = time.time_ns()
        entities: dict[str, int] = {}
        newest = [0]

        def on_message(payload: bytes) -> None:
            chunk = chunk_of(payload)
            if chunk is None or chunk.store_kind != STORE_RECORDING or chunk.newest_time_ns is None:
                return
            assert chunk.recording_id == f"run-{run_id}"
            entities[chunk.entity] = entities.get(chunk.entity, 0) + 1
            newest[0] = max(newest[0], chunk.newest_time_ns)

        got = read_messages(
            http,
            READ_MESSAGES,
            on_message=on_message,
            timeout=60,
            until=lambda _: newest[0] > connected_ns + 1_000_000_000 and entities.get("/log/signals", 0) >= 5,
        )
        assert got.ended_by == "until", (got.ended_by, entities)
        # the probe's six variables (one group, `signals`) are one entity: one message per batch
        assert "/log/signals" in entities, entities
        assert not [e for e in entities if e.startswith("/log/signals/")], entities
        assert set(entities) <= {"/log/signals", "/telemetry/enc", "/telemetry/pwm", "/telemetry/xeno2ros"}, entities
        # samples logged a second after the viewer connected reached it while it stayed connected
        assert newest[0] > connected_ns + 1_000_000_000
    finally:
        http.close()


def test_no_live_stream_before_the_first_run(tmp_path: Path) -> None:
    s = start(tmp_path / "data")
    try:
        info = s.http.get("/api/logs/rerun").json()
        assert info["live_run"] is None and info["live_url"] == "" and "no run" in info["live_reason"]
        assert info["live_reason"] == NO_LIVE_STREAM  # the same words as for someone else's run
        r = s.http.post(READ_MESSAGES, headers=GRPC_WEB, content=b"\0" * 5)
        assert r.status_code == 404 and r.headers["grpc-status"] == "5"
        assert urllib.parse.unquote(r.headers["grpc-message"]) == NO_LIVE_STREAM
        assert not live_proxies(s)
    finally:
        stop_server(s)


def test_the_live_stream_does_not_go_through_a_web_proxy_of_the_environment(tmp_path: Path) -> None:
    """A lab behind a web proxy sets HTTP_PROXY / ALL_PROXY for every process, the appliance's too.
    The read route forwards a viewer's stream to the run's proxy on 127.0.0.1, and httpx by default
    takes its proxy from the environment: that loopback request went to the lab's proxy, and the
    viewer got a 502 ("the live stream does not answer") instead of the run. Here the
    environment's proxy is a port nothing listens on."""
    nowhere = f"http://127.0.0.1:{free_port()}"
    s = start(tmp_path / "data", env={"HTTP_PROXY": nowhere, "http_proxy": nowhere, "ALL_PROXY": nowhere})
    try:
        run_id = run_probe(s)
        got = read_messages(s.http, READ_MESSAGES, until=lambda d: f"run-{run_id}".encode() in d and b"ratio" in d)
        assert got.status == 200, (got.status, urllib.parse.unquote(got.headers.get("grpc-message", "")))
        assert f"run-{run_id}".encode() in got.data and b"ratio" in got.data, got.data[:200]
    finally:
        stop_server(s)


def test_the_live_page_does_not_wait_for_the_proxy_to_start(tmp_path: Path) -> None:
    """A live viewer's page starts the run's proxy process (the run's first viewer) and its
    recording, so that the stream holds the live edge when the viewer's app asks for it seconds
    later. The page used to be served only once rerun's process listened (0.2-0.5 s under load),
    and the viewer's whole start waited with it. Here rerun's start is held (the `nice` it is
    started through waits while a file exists): the page is served all the same, and a stream
    asked for meanwhile waits for the start and gets the run (not a 502 from a port nobody
    listens on yet)."""
    import os
    import shutil
    import stat

    hold = tmp_path / "hold"
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    nice = bin_dir / "nice"
    nice.write_text(f'#!/bin/sh\nwhile [ -e "{hold}" ]; do sleep 0.05; done\nexec {shutil.which("nice")} "$@"\n')
    nice.chmod(nice.stat().st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
    s = start(tmp_path / "data", env={"PATH": f"{bin_dir}:{os.environ['PATH']}"})
    try:
        assert s.http.get("/rerun/index.html", timeout=600).status_code == 200  # the viewer's files prepared
        run_id = run_probe(s)
        live_url = s.http.get("/api/logs/rerun").json()["live_url"]
        hold.write_text("")
        page = s.http.get("/rerun/index.html", params={"url": live_url}, timeout=10)
        assert page.status_code == 200  # (before: it waited for rerun to listen, then gave up after 20 s)
        got: list = []
        reader = threading.Thread(
            target=lambda: got.append(
                read_messages(s.http, READ_MESSAGES, until=lambda d: f"run-{run_id}".encode() in d and b"ratio" in d)
            )
        )
        reader.start()
        time.sleep(1.0)  # time passing: the stream's request reaches the route while rerun's start is held
        hold.unlink()
        reader.join(60)
        assert got, "no answer to the stream"
        assert got[0].status == 200, (got[0].status, urllib.parse.unquote(got[0].headers.get("grpc-message", "")))
        assert f"run-{run_id}".encode() in got[0].data and b"ratio" in got[0].data, got[0].data[:200]
    finally:
        hold.unlink(missing_ok=True)
        stop_server(s)


def _rerun_threads(pid: int) -> int:
    """The rerun SDK's recording threads in process `pid` (RecordingStream, ChunkBatcher::...)."""
    n = 0
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            n += (task / "comm").read_text().startswith(("RecordingStream", "ChunkBatcher"))
        except OSError:
            continue
    return n


def test_runs_watched_live_leave_no_recording_behind(lan) -> None:
    """Each run watched live has a recording of its own and a blueprint; the rerun SDK keeps
    every recording made from Python until swept, and every blueprint it sends (two threads and
    their memory each, for the appliance's lifetime: bench/appliance/practical.py). The same
    program watched in three runs: after the first, the appliance's rerun threads stay as many."""
    server, _ = lan
    counts = []
    for _ in range(3):
        run_id = run_probe(server)
        got = read_messages(server.http, READ_MESSAGES, until=lambda d: f"run-{run_id}".encode() in d and b"ratio" in d)  # noqa: B023
        assert b"ratio" in got.data
        server.stop_run()
        # the run's recording is flushed and swept in the background after the run's end
        wait_for(lambda: _rerun_threads(server.proc.pid) <= 2, timeout=20, what="the run's recording swept")
        counts.append(_rerun_threads(server.proc.pid))
    assert counts[1] == counts[2] == counts[0], counts


def test_an_ended_runs_proxy_runs_only_while_watched(lan) -> None:
    """Issue 30 item 4: the live proxy (a rerun process of ~33 MB) ran from each run's start,
    watched or not, and was kept after its run ended until the next run. Now it starts at the
    run's first viewer, stays while a viewer reads the ended run, stops when the last leaves,
    and a viewer of the ended run starts it again (an empty stream: the run's data is in its log)."""
    server, url = lan
    http = login_client(url, ADMIN_USER, ADMIN_PASSWORD)
    try:
        # no viewer: no proxy process, during the run or after it
        server.wait_cycles(run_probe(server, http), 200)
        assert not live_proxies(server), "a live proxy runs for a run nobody watches"
        server.stop_run()
        assert not live_proxies(server)

        # a viewer connected across the run's end keeps it until it leaves
        run_id = run_probe(server, http)
        got: dict[str, object] = {}

        def watch() -> None:
            got["stream"] = read_messages(http, READ_MESSAGES, timeout=120, quiet=15)

        viewer = threading.Thread(target=watch)
        viewer.start()
        wait_for(lambda: http.get("/api/logs/rerun").json()["live_viewers"] >= 1, timeout=20, what="the viewer")
        server.stop_run()
        wait_for(lambda: not http.get("/api/logs/rerun").json()["live_running"], timeout=30, what="the run's end")
        procs = live_proxies(server)
        if viewer.is_alive():  # (it leaves 15 s after the stream went quiet)
            assert procs, "the ended run's proxy stopped while a viewer read it"
        viewer.join(60)
        assert got["stream"].ended_by == "quiet"  # type: ignore[attr-defined]
        wait_for(lambda: not live_proxies(server), timeout=20, what="the proxy to stop after its last viewer")
        info = http.get("/api/logs/rerun").json()
        assert info["live_run"] == run_id and not info["live_running"] and info["live_url"]

        # a viewer of the ended run: the proxy starts again, answers, and stops after it
        again = read_messages(http, READ_MESSAGES, timeout=10, quiet=2)
        assert again.status == 200 and again.ended_by == "quiet", again.headers
        wait_for(lambda: not live_proxies(server), timeout=20, what="the restarted proxy to stop")
    finally:
        http.close()
