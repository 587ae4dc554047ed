"""The 3D view page in a real browser: the viser scene opens in a tab of its own through the
appliance's /viser/ proxy (same origin, behind the login; nothing fetched from anywhere else), the
Jiwy's pan joint follows a setpoint change on the simulated bench, and the dashboard's main thread
is never the scene's (issue 31 bug 7: leaving the embedded scene froze the dashboard for 5-8 s)."""

from __future__ import annotations

import urllib.parse
from pathlib import Path

from xrf_testing.harness import Server

REPO_ROOT = Path(__file__).resolve().parents[2]
SHOTS = REPO_ROOT / "test-results"
# The scene's tab is kept busy for BUSY_MS while the user leaves the 3D page. If the scene shared
# the dashboard's main thread (the embedded scene did: leaving it froze the dashboard for 5-8 s),
# no dashboard timer could run inside that stretch. So the test asks that the dashboard's 20 ms
# timer ran in each of its SLICES parts: a bound on the pause (3 s) flaked on a loaded 2-core
# machine, where the other tab's busy loop and the load starve the dashboard's renderer for
# seconds (it runs late, not never); a shared thread runs it never.
BUSY_MS = 6000
SLICES = 3

# In the dashboard: a 20 ms timer that records when it ran (wall clock, as the scene's tab's) until
# window._stopTicks().
TICKS = """(() => { window._ticks = []; let on = true;
  window._stopTicks = () => { on = false; return window._ticks; };
  (function tick() { window._ticks.push(Date.now()); if (on) setTimeout(tick, 20); })(); })()"""


def test_view3d_loads_and_follows_a_jiwy_setpoint(server: Server, browser) -> None:
    server.stop_run()
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    errors: list[str] = []
    requests: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    sockets: list[str] = []
    page.on("request", lambda r: requests.append(r.url))
    page.on("websocket", lambda w: sockets.append(w.url))
    page.goto(server.url + "/#view3d")
    page.wait_for_function("document.getElementById('conn').textContent === 'connected'")
    assert page.is_visible("#nav a[data-page=view3d]")

    # No scene in the dashboard: no iframe, no canvas (the scene's WebGL would share this page's
    # main thread). The button opens /viser/ on the dashboard's own origin in a tab of its own.
    viser_port = server.http.get("/api/viz").json()["port"]
    page.wait_for_function("document.getElementById('v3d-link').href.endsWith('/viser/')")
    assert page.evaluate("document.querySelectorAll('iframe, #page-view3d canvas').length") == 0
    with page.context.expect_page() as opened:
        page.click("#v3d-open")
    scene = opened.value
    scene.on("pageerror", lambda e: errors.append(str(e)))
    scene.on("request", lambda r: requests.append(r.url))
    scene.on("websocket", lambda w: sockets.append(w.url))
    scene.wait_for_load_state()
    assert scene.url.startswith(server.url + "/viser/"), scene.url  # viser adds ?websocket=<its ws URL>
    assert scene.evaluate("window.opener") is None  # noopener: a browsing context group of its own
    # viser's client starts there: its React root fills with the 3D canvas, and its WebSocket goes
    # through the proxy too (never to viser's port); our tab script is there (Esc stops the run).
    scene.locator("canvas").first.wait_for(state="attached", timeout=60_000)
    scene.wait_for_function("window.xrfRerunTab !== undefined")

    # A Jiwy run in RUN, then a setpoint from the dashboard's own WebSocket.
    server.start_run("jiwy")
    with server.ws() as ws:
        ws.wait_state("IDLE", 20)
        ws.command("initialise")
        ws.wait_state("INITIALISED")
        ws.command("start")
        ws.wait_state("RUN")
    page.wait_for_function(
        "window.xrf.view3d && window.xrf.view3d.kind === 'pan_tilt' && window.xrf.view3d.mode === 'live'"
    )
    pan0 = page.evaluate("window.xrf.view3d.joints.pan")
    assert abs(pan0) < 0.05
    # The setpoint goes out through the dashboard's WebSocket, every 0.5 s until the view shows it.
    page.evaluate("""window._sp = setInterval(() => xrf.send({type: 'setpoint',
        fields: {pan_setpoint: 0.5, tilt_setpoint: 0.0}}), 500)""")
    page.wait_for_function("Math.abs(window.xrf.view3d.joints.pan - 0.5) < 0.03", timeout=20_000)
    page.evaluate("clearInterval(window._sp)")
    # The server-side scene state agrees, and the page shows the numbers and the ghost.
    state = server.http.get("/api/viz/state").json()
    assert abs(state["joints"]["pan"] - 0.5) < 0.03 and state["ghost"]["pan"] == 0.5
    page.wait_for_function("document.getElementById('v3d-values').textContent.includes('setpoint')")
    assert "pan 2" in page.inner_text("#v3d-values")  # 0.5 rad = 28.6°
    # Drawn by viz/urdf_view.py, not viser's ViserUrdf: the appliance has not loaded the trimesh
    # stack's native libraries (shapely's GEOS, embree), 77 MB resident with ViserUrdf.
    maps = Path(f"/proc/{server.proc.pid}/maps").read_text()
    assert "shapely" not in maps and "embree" not in maps, "the appliance loaded shapely/embree for the 3D view"

    SHOTS.mkdir(exist_ok=True)
    page.screenshot(path=str(SHOTS / "view3d.png"), full_page=True)
    scene.screenshot(path=str(SHOTS / "view3d-scene.png"))

    # The dashboard answers while the scene's tab is busy and the user leaves the 3D page: the
    # scene's main thread is not the dashboard's. (A same-origin iframe's is: the dashboard then
    # pauses for the whole busy stretch, as it froze tearing down the embedded scene.)
    page.evaluate(TICKS)
    page.click("#nav a[data-page=bench]")
    page.wait_for_function("document.getElementById('page-view3d').classList.contains('hidden')")
    # Returns when the scene's tab has run its loop to the end; the dashboard's timer ran meanwhile.
    busy_from, busy_to = scene.evaluate(
        f"(() => {{ const t = Date.now(); while (Date.now() - t < {BUSY_MS}); return [t, Date.now()]; }})()"
    )
    ticks = page.evaluate("window._stopTicks()")
    assert busy_to - busy_from >= BUSY_MS
    step = (busy_to - busy_from) / SLICES
    ran = [sum(busy_from + i * step <= t < busy_from + (i + 1) * step for t in ticks) for i in range(SLICES)]
    assert all(ran), f"the dashboard's timer ran {ran} times in the {SLICES} parts of the scene's busy {BUSY_MS} ms"
    server.stop_run()

    # Offline: every request of the page and of the scene's tab went to the appliance's host.
    hosts = {urllib.parse.urlsplit(u).hostname for u in requests if u.startswith(("http:", "https:", "ws:", "wss:"))}
    assert hosts <= {"127.0.0.1"}, hosts
    app_port = urllib.parse.urlsplit(server.url).port
    net = [u for u in requests + sockets if u.startswith(("http:", "https:", "ws:", "wss:"))]
    assert {urllib.parse.urlsplit(u).port for u in net} == {app_port}, net
    assert server.url.replace("http://", "ws://") + "/viser" in sockets, sockets
    assert viser_port != app_port
    assert not errors, errors
    scene.close()
    page.close()
