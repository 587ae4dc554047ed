"""A 4-hour practical without friction (issue 19): each bug found by walking through a practical
in Chromium, reproduced in the browser. Each test failed on the dashboard before its fix.

XRF_TEST_FRONTEND=<folder> serves another frontend (an older one exported with `git archive`),
to see these tests fail against it."""

from __future__ import annotations

import io
import os
import signal
import tarfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from xrf_testing.harness import Server, browser_login, shared_builds_root, start_server, stop_server, wait_for
from xrf_testing.projects_support import reachable_tmp

REPO = Path(__file__).resolve().parents[2]

BASE = REPO / "student_projects/templates/base"
TABLET = {"width": 768, "height": 1024}


@pytest.fixture(scope="module")
def server() -> Iterator[Server]:
    extra = {"frontend_dir": os.environ["XRF_TEST_FRONTEND"]} if os.environ.get("XRF_TEST_FRONTEND") else {}
    # A data folder the build user (xrf-build) can reach: not under root's private /tmp/pytest-of-root.
    s = start_server(reachable_tmp("ui19-data"), shared_builds_root(), **extra)
    yield s
    stop_server(s)


def targz(name: str, edit: dict[str, tuple[str, str]] | None = None) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as t:
        for p in sorted(BASE.rglob("*")):
            if not p.is_file() or "build" in p.relative_to(BASE).parts:
                continue
            rel = p.relative_to(BASE).as_posix()
            data = p.read_text()
            old, new = (edit or {}).get(rel, ("", ""))
            if old:
                assert old in data
                data = data.replace(old, new)
            raw = data.encode()
            info = tarfile.TarInfo(f"{name}/{rel}")
            info.size = len(raw)
            t.addfile(info, io.BytesIO(raw))
    return buf.getvalue()


def project(http, name: str, edit: dict[str, tuple[str, str]] | None = None) -> tuple[int, dict]:  # noqa: ANN001
    """Upload and build a project over the API; (project id, the finished build)."""
    r = http.post("/api/projects", files={"file": (f"{name}.tar.gz", targz(name, edit), "application/gzip")})
    assert r.status_code == 201, r.text
    pid = r.json()["project"]["id"]
    b = http.post(f"/api/projects/{pid}/builds").json()
    done = wait_for(
        lambda: (x := http.get(f"/api/projects/{pid}/builds/{b['id']}").json())["status"] in ("ok", "failed") and x,
        300,
        f"build of {name}",
    )
    return pid, done


def state_is(page, name: str, timeout: float = 15_000) -> None:  # noqa: ANN001
    page.wait_for_function(f"document.getElementById('state-name').textContent === {name!r}", timeout=timeout)


def to_run(server: Server) -> None:
    for cmd in ("initialise", "start"):  # each answered once the loop handled it
        assert server.http.post("/api/runs/current/command", json={"cmd": cmd}).json()["accepted"]


def test_esc_stops_from_inside_the_3d_view_and_the_rerun_viewer(server: Server, browser) -> None:  # noqa: ANN001
    server.stop_run()
    server.start_run("relbot")
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.goto(server.url + "/")
    state_is(page, "IDLE", 120_000)
    page.click("#commands [data-cmd=initialise]")
    state_is(page, "INITIALISED")
    page.click("#commands [data-cmd=start]")
    state_is(page, "RUN")

    # Focus inside the 3D scene (viser), which opens in a tab of its own (issue 31 bug 7), then Esc:
    # the scene's page has our tab script (server/http/viser.py), which stops over HTTP.
    page.goto(server.url + "/#view3d")
    with page.context.expect_page() as opened:
        page.click("#v3d-open")
    scene = opened.value
    scene.wait_for_function("window.xrfRerunTab !== undefined", timeout=60_000)
    scene.locator("canvas").first.wait_for(state="attached", timeout=60_000)
    scene.mouse.click(300, 300)
    with server.ws() as ws:
        scene.keyboard.press("Escape")
        ws.wait_for(lambda m: m.get("type") == "state" and m.get("name") in ("STOPPING", "STOPPED"), 15)
    scene.close()
    page.bring_to_front()  # the dashboard's tab, in the background since the scene's opened
    state_is(page, "STOPPED")

    # Again from inside the rerun viewer, which opens in a tab of its own (no dashboard there:
    # the viewer page's own script sends the stop over HTTP). The state is read through the API
    # (the appliance's WebSocket), not from the dashboard's tab, which is in the background.
    for cmd in ("reset", "start"):
        assert server.http.post("/api/runs/current/command", json={"cmd": cmd}).json()["accepted"]
    state_is(page, "RUN")
    page.goto(server.url + "/#runs")
    with page.context.expect_page() as opened:
        page.click("#rr-live")
    viewer = opened.value
    viewer.wait_for_function("() => window._handle !== undefined", timeout=240_000)  # rerun's app started
    # (the mouse itself: a locator's click waits for frames a software-rendered viewer is slow to draw)
    viewer.mouse.click(200, 200)
    assert viewer.evaluate("document.activeElement.id") == "the_canvas_id"
    with server.ws() as ws:
        viewer.keyboard.press("Escape")
        ws.wait_for(lambda m: m.get("type") == "state" and m.get("name") in ("STOPPING", "STOPPED"), 15)
    # the note, once the viewer's busy thread handles the answer
    viewer.wait_for_function(
        "() => (document.getElementById('xrf-stop-note') || {}).textContent === "
        "'Stop sent (Esc): the controller is stopping.'",
        timeout=60_000,
        polling=250,
    )

    # Esc again, now in STOPPED: the dashboard's rule ends the run.
    viewer.keyboard.press("Escape")
    viewer.wait_for_function(
        "() => document.getElementById('xrf-stop-note').textContent.startsWith('Run ended')",
        timeout=60_000,
        polling=250,
    )
    assert server.http.get("/api/runs?limit=1").json()[0]["status"] == "ended"
    page.context.close()
    server.stop_run()


def test_projects_page_shows_the_selected_projects_build(server: Server, browser) -> None:  # noqa: ANN001
    good, _ = project(server.http, "good_one")
    bad, b = project(
        server.http,
        "broken_one",
        {"src/Template.cpp": ("xeno_msg.pos_left = ros_msg.steer_left;", "xeno_msg.pos_left = ros_msg.no_such_field;")},
    )
    assert b["status"] == "failed"
    page = browser.new_page(viewport=TABLET)
    page.goto(server.url + "/#projects")
    page.click(f"#proj-list li[data-id='{bad}']")
    page.wait_for_selector("#proj-diags li.diag.error.clickable")
    page.click("#proj-diags li.diag.error.clickable >> nth=0")
    page.wait_for_selector("#proj-source .srcline.hl")
    # The good project: none of the broken one's build, errors or source may stay.
    page.click(f"#proj-list li[data-id='{good}']")
    page.wait_for_function("document.getElementById('proj-name').textContent.startsWith('good_one')")
    page.wait_for_selector("#proj-builds tr.current.st-ok")
    page.wait_for_timeout(500)
    assert page.locator("#proj-diags li.error").count() == 0
    assert "no_such_field" not in page.inner_text("#proj-detail")
    assert page.is_hidden("#proj-source")
    assert "ok" in page.inner_text("#proj-build-title")
    page.close()


def test_bench_offers_the_project_build_that_ran(server: Server, browser) -> None:  # noqa: ANN001
    server.stop_run()
    pid, b = project(server.http, "mine_to_run")
    assert b["status"] == "ok"
    page = browser.new_page(viewport=TABLET)
    page.goto(server.url + "/")
    page.wait_for_selector("#build-select option[value=relbot]", state="attached")
    page.select_option("#build-select", "relbot")  # the example picked before
    name = f"project-{pid}-build-{b['id']}"
    # Run the project from elsewhere (the Projects page's Run button does this).
    r = server.http.post(f"/api/projects/{pid}/builds/{b['id']}/run", json={})
    assert r.status_code == 201, r.text
    page.wait_for_function(f"document.getElementById('build-select').value === {name!r}", timeout=15_000)
    assert "mine_to_run" in page.locator("#build-select option:checked").inner_text()
    server.stop_run()
    state_is(page, "ENDED")
    # "Start run" here starts the project again, not the example.
    page.click("#btn-start-run")
    run = wait_for(
        lambda: (x := server.http.get("/api/runs?limit=1").json()[0])["status"] == "running" and x, 60, "a run"
    )
    assert run["build"] == name
    server.stop_run()
    page.close()


def test_monitor_follows_after_visiting_another_page(server: Server, browser) -> None:  # noqa: ANN001
    page = browser.new_page(viewport=TABLET)
    page.goto(server.url + "/")
    page.wait_for_function("document.getElementById('conn').textContent === 'connected'")

    def lines(n: int, tag: str) -> None:  # every bad message gets an error line in the monitor
        page.evaluate(f"for (let i = 0; i < {n}; i++) xrf.send({{type: 'no-such-{tag}-' + i}})")
        page.wait_for_function(f"document.getElementById('monitor').textContent.includes('no-such-{tag}-{n - 1}')")

    lines(60, "a")
    page.goto(server.url + "/#projects")
    lines(60, "b")
    page.goto(server.url + "/#bench")
    page.wait_for_timeout(300)
    at_bottom = "(() => { const p = document.getElementById('monitor'); return p.scrollTop + p.clientHeight >= p.scrollHeight - 4; })()"
    assert page.evaluate(at_bottom)
    lines(20, "c")
    page.wait_for_timeout(100)
    assert page.evaluate(at_bottom)
    page.close()


def test_crash_in_the_sticky_strip_and_nothing_shifts(server: Server, browser) -> None:  # noqa: ANN001
    server.stop_run()
    page = browser.new_page(viewport=TABLET)
    page.goto(server.url + "/")
    page.wait_for_function("document.getElementById('conn').textContent === 'connected'")
    page.wait_for_timeout(500)
    top = "document.getElementById('page-bench').getBoundingClientRect().top + window.scrollY"
    before = page.evaluate(top)
    run = server.start_run("relbot")
    to_run(server)
    state_is(page, "RUN")
    assert page.inner_text("#strip-state") == "RUN"
    # A deadline-miss alarm and a notice come and go: the page does not move.
    page.evaluate("showAlarm({kind: 'deadline_miss', message: 'a deadline was missed'})")
    page.evaluate("xrf.notice && xrf.notice('a notice', 1000)")
    assert page.evaluate(top) == before
    # Scrolled down to the setpoints, the crash is on screen and the state is not RUN.
    page.locator("#panel-setpoints").scroll_into_view_if_needed()
    page.mouse.wheel(0, 600)
    os.kill(run["pid"], signal.SIGKILL)
    page.wait_for_function("/crashed/.test(document.getElementById('alarm-text').textContent)")
    assert page.is_visible("#alarm")
    box = page.locator("#alarm").bounding_box()
    assert box is not None and box["y"] >= 0 and box["y"] + box["height"] <= TABLET["height"], box
    assert page.evaluate("window.scrollY") > 100  # really scrolled
    page.wait_for_function("document.getElementById('strip-state').textContent === 'CRASHED'")
    bar = page.locator(".topbar").bounding_box()
    assert bar["y"] == 0 and bar["height"] < 260, bar  # sticky, and not a quarter of the tablet
    for sel in ("#strip-state", "#lease", "#alarm"):  # state, lease and alarm: one strip in the bar
        box = page.locator(sel).bounding_box()
        assert box and box["y"] >= 0 and box["y"] + box["height"] <= bar["height"], (sel, box, bar)
    page.mouse.wheel(0, -5000)
    page.wait_for_timeout(200)
    assert page.evaluate(top) == before
    page.close()


def test_setpoints_need_the_bench_and_reset_zeroes_them(server: Server, raw_browser) -> None:  # noqa: ANN001
    server.stop_run()
    password = server.create_user("sp-student", "student")
    http, _ = server.login("sp-student", password)
    try:
        assert http.post("/api/lease/take").status_code == 200
        assert http.post("/api/runs", json={"build": "relbot"}, timeout=300).status_code == 201
        ctx = raw_browser.new_context(viewport=TABLET)
        page = ctx.new_page()
        browser_login(page, server.url, "sp-student", password)
        state_is(page, "IDLE", 60_000)
        page.click("#commands [data-cmd=initialise]")
        state_is(page, "INITIALISED")
        page.click("#commands [data-cmd=start]")
        state_is(page, "RUN")
        page.fill("#sp-steer_left", "2")
        page.wait_for_function("Math.abs(xrf.lastTelemetry.xeno2ros.pos_left - 2) < 0.1", timeout=15_000)
        # A reset starts the setpoints over: zero on the appliance and on the page.
        page.click("#commands [data-cmd=reset]")
        state_is(page, "INITIALISED")
        page.wait_for_function("document.getElementById('sp-steer_left').value === '0'")
        with server.ws() as ws:
            assert ws.wait_type("run", seen=True)["setpoint"]["steer_left"] == 0
        page.click("#commands [data-cmd=start]")
        state_is(page, "RUN")
        page.wait_for_timeout(1000)
        assert abs(page.evaluate("xrf.lastTelemetry.xeno2ros.pos_left")) < 0.1
        # An educator takes the bench over: the student's controls are off, not silently refused.
        assert server.http.post("/api/lease/take").status_code == 200
        page.wait_for_function("document.getElementById('sp-steer_left').disabled")
        assert page.is_disabled("#sp-range-steer_left")
        # And the 3D view's replay says why it cannot, on the page (it was an alert).
        server.stop_run()
        page.goto(server.url + "/#view3d")
        page.wait_for_function("document.querySelectorAll('#v3d-runs option').length > 1", timeout=15_000)
        page.select_option("#v3d-runs", index=1)
        page.click("#v3d-replay")
        page.wait_for_function("/bench/.test(document.getElementById('v3d-message').textContent)")
        ctx.close()
    finally:
        server.http.post("/api/lease/release")
        http.close()


def test_runs_page_keeps_the_users_choice(server: Server, browser) -> None:  # noqa: ANN001
    server.stop_run()
    run = server.start_run("relbot")
    to_run(server)
    server.wait_cycles(run["id"], 100)
    server.stop_run()
    live = server.start_run("relbot")  # a live run, so "Live plots" has something to show
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.goto(server.url + "/#runs")
    row = page.locator(f"#runs-row-{run['id']}")
    row.wait_for()
    # A click held across the table's 2 s refresh still selects the run.
    box = row.bounding_box()
    page.mouse.move(box["x"] + 20, box["y"] + box["height"] / 2)
    page.mouse.down()
    page.wait_for_timeout(2600)
    page.mouse.up()
    page.wait_for_selector("#panel-run-logs:not(.hidden)", timeout=5000)
    assert f"#{run['id']}" in page.inner_text("#rl-title")
    # A slow appliance: "Live plots" answers late, after "Open in rerun" was clicked: the newest
    # click wins, also over the 2 s poll that follows the live stream.
    # (Delayed in the page: a route handler that sleeps holds Playwright's own event loop, and
    # with it the next click, so the late answer would not be late.)
    page.evaluate("""() => { const f = window.fetch; let n = 0;
      window.fetch = (u, o) => String(u).includes('/api/logs/rerun') && ++n === 1
        ? new Promise((r) => setTimeout(r, 1500)).then(() => f(u, o)) : f(u, o); }""")
    viewers: list = []  # each opens in a tab of its own: its page, and the URL it was opened with
    page.context.on("page", lambda p: viewers.append(p))
    opened: list[str] = []  # (the viewer rewrites its address bar once it runs)
    page.context.on("request", lambda r: opened.append(r.url) if "/rerun/?url=" in r.url else None)
    page.evaluate("document.getElementById('rr-live').click()")  # what page.show() used to do by itself
    page.locator(".open-rrd").first.click()
    for _ in range(60):  # Playwright delivers its events while it is called: not time.sleep
        if viewers:
            break
        page.wait_for_timeout(250)
    page.wait_for_timeout(5000)
    # one tab, the .rrd: the late answer to "Live plots" and the 2 s poll opened none
    assert len(viewers) == 1 and len(opened) == 1, opened
    assert "%2Fapi%2Flogs%2Fviewer%2F" in opened[0] and opened[0].endswith(".rrd"), opened  # its own link
    assert "%2Fapi%2Flogs%2Fviewer%2F" in page.get_attribute("#rr-link", "href")
    assert "(.rrd)" in page.inner_text("#rr-what")
    page.context.close()
    assert live["id"] > run["id"]
    server.stop_run()


def rerun_viewer(ctx):  # noqa: ANN001, ANN201
    """The rerun viewer wherever the dashboard opened it (a tab of its own, or an embedded frame
    of an older frontend), once rerun's app runs in it; else None."""
    for p in ctx.pages:
        for f in p.frames:
            if "/rerun/" in f.url:
                try:
                    if f.evaluate("window._handle !== undefined"):
                        return f
                except Exception:  # noqa: BLE001  (a frame navigating: look again)
                    pass
    return None


def test_dashboard_stays_connected_while_the_viewer_renders(server: Server, browser) -> None:  # noqa: ANN001
    """Issue 19 item 9: the rerun viewer embedded in the dashboard froze the dashboard's main
    thread while it started and drew (12 s to 177 s on a software GPU): nothing was read from the
    WebSocket, it was closed (1006) and Esc did nothing. Opened in a tab of its own, the dashboard
    keeps its connection and its messages while the viewer loads and renders the live run."""
    server.stop_run()
    server.start_run("relbot")
    to_run(server)
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    ctx = page.context
    try:
        # The dashboard's WebSocket as DevTools sees it: every socket opened and closed.
        cdp = ctx.new_cdp_session(page)
        sockets = {"created": 0, "closed": 0}
        cdp.on("Network.webSocketCreated", lambda ev: sockets.__setitem__("created", sockets["created"] + 1))
        cdp.on("Network.webSocketClosed", lambda ev: sockets.__setitem__("closed", sockets["closed"] + 1))
        cdp.send("Network.enable")
        page.goto(server.url + "/")
        state_is(page, "RUN", 60_000)
        # When each status message (telemetry, timing) arrived, and the page's longest pause.
        page.evaluate("""() => {
          window.t19 = {msgs: [], maxPause: 0, last: performance.now()};
          for (const k of ["telemetry", "timing"]) xrf.on(k, () => t19.msgs.push(performance.now()));
          setInterval(() => { const now = performance.now();
            t19.maxPause = Math.max(t19.maxPause, now - t19.last); t19.last = now; }, 100);
        }""")
        page.goto(server.url + "/#runs")
        clicked = page.evaluate("performance.now()")
        page.click("#rr-live")
        page.goto(server.url + "/#bench")
        viewer = None
        deadline = time.monotonic() + 300
        while viewer is None:  # the 43 MB viewer starts on a software renderer
            assert time.monotonic() < deadline, "the rerun viewer did not start"
            page.wait_for_timeout(1000)
            viewer = rerun_viewer(ctx)
        started = page.evaluate("performance.now()")
        page.wait_for_timeout(20_000)  # while it reads the live stream and draws
        t = page.evaluate("t19")
        end = page.evaluate("performance.now()")
        # From the click to now: the viewer's start (wasm download and compile) and its drawing.
        msgs = [m for m in t["msgs"] if m >= clicked]
        gaps = [b - a for a, b in zip([clicked] + msgs, msgs + [end])]
        print(
            f"dashboard from the click ({(started - clicked) / 1000:.1f} s to the viewer's start, then 20 s): "
            f"{len(msgs)} status messages, longest gap {max(gaps):.0f} ms, "
            f"longest main-thread pause {t['maxPause']:.0f} ms, sockets {sockets}"
        )
        assert sockets == {"created": 1, "closed": 0}, sockets
        assert page.evaluate("xrf.ws.readyState") == 1
        assert len(msgs) > 20 and max(gaps) < 3000, (len(msgs), max(gaps))
    finally:
        ctx.close()
        server.stop_run()


def test_header_follows_the_run_and_the_jitter_axis_fits(server: Server, browser) -> None:  # noqa: ANN001
    server.stop_run()
    assert server.http.get("/api/bench").json()["sim"] == "relbot"
    server.start_run("jiwy", sim="jiwy")
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.goto(server.url + "/")
    page.wait_for_function("/jiwy/.test(document.getElementById('bench').textContent)", timeout=15_000)
    to_run(server)
    # The jitter histogram's y axis is wide enough for its labels (10,000 was clipped). A real
    # timing message, its counts as after some minutes of running (cycles in one bucket > 10,000).
    page.evaluate("xrf.on('timing', (m) => { window.lastTiming = m; })")
    page.wait_for_function("window.lastTiming && window.lastTiming.jitter.counts.length > 0", timeout=30_000)
    page.evaluate("xrf.ws.onclose = null; xrf.ws.close()")  # no real message after this one
    page.evaluate("""() => { const m = window.lastTiming;
      applyTiming({...m, jitter: {...m.jitter, counts: m.jitter.counts.map((c) => c * 1000 + 1)}}); }""")
    page.wait_for_timeout(300)
    fit = page.evaluate("""() => {
      const u = xrf.plots.jitter.plot, ax = u.axes[1];
      const ctx = document.createElement('canvas').getContext('2d');
      ctx.font = ax.font[0];
      const widest = Math.max(...ax._values.map((v) => ctx.measureText(String(v)).width)) / devicePixelRatio;
      return {size: ax._size, widest, labels: ax._values, space: ax._size - (ax.ticks.size || 0) - (ax.gap || 0)};
    }""")
    assert fit["space"] >= fit["widest"], fit
    server.stop_run()
    page.goto(server.url + "/")  # (its WebSocket was closed above)
    page.wait_for_function("/relbot/.test(document.getElementById('bench').textContent)", timeout=15_000)
    page.close()


def test_every_page_fits_a_tablet(server: Server, browser) -> None:  # noqa: ANN001
    page = browser.new_page(viewport=TABLET)
    page.goto(server.url + "/")
    page.wait_for_function("document.querySelectorAll('#nav a').length > 5")
    for page_id in page.evaluate("[...document.querySelectorAll('#nav a')].map((a) => a.dataset.page)"):
        page.goto(server.url + "/#" + page_id)
        page.wait_for_timeout(400)
        width = page.evaluate("document.documentElement.scrollWidth")
        assert width <= TABLET["width"], (page_id, width)
        page.mouse.wheel(0, 3000)
        bar = page.locator(".topbar").bounding_box()
        assert bar["y"] == 0 and bar["height"] < 260, (page_id, bar)
        for sel in ("#btn-estop", "#strip-state", "#lease"):
            box = page.locator(sel).bounding_box()
            assert box and 0 <= box["y"] and box["y"] + box["height"] <= bar["height"], (page_id, sel, box)
    page.close()
