"""The 3D view page in a real browser: the viser scene loads in the dashboard's iframe through the
appliance's /viser/ proxy (same origin, behind the login; nothing fetched from anywhere else), and the Jiwy's pan joint follows a
setpoint change on the simulated bench."""

from __future__ import annotations

import urllib.parse
from pathlib import Path

from xrf_testing.harness import Server

REPO_ROOT = Path(__file__).resolve().parents[2]
SHOTS = REPO_ROOT / "test-results"


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

    # The iframe points at the dashboard's own origin, /viser/ (viser's own port is loopback only).
    viser_port = server.http.get("/api/viz").json()["port"]
    page.wait_for_function("document.getElementById('v3d-frame') && document.getElementById('v3d-frame').src !== ''")
    src = page.get_attribute("#v3d-frame", "src")
    assert src == server.url + "/viser/", src
    # viser's client starts inside it: its React root fills with the 3D canvas, and its WebSocket
    # goes through the proxy too (never to viser's port).
    frame = page.frame_locator("#v3d-frame")
    frame.locator("canvas").first.wait_for(state="attached", timeout=30_000)

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

    SHOTS.mkdir(exist_ok=True)
    page.screenshot(path=str(SHOTS / "view3d.png"), full_page=True)
    server.stop_run()

    # Offline: every request of the page and its iframe went to the appliance's host.
    hosts = {urllib.parse.urlsplit(u).hostname for u in requests if u.startswith(("http:", "https:", "ws:", "wss:"))}
    assert hosts <= {"127.0.0.1"}, hosts
    app_port = urllib.parse.urlsplit(server.url).port
    net = [u for u in requests + sockets if u.startswith(("http:", "https:", "ws:", "wss:"))]
    assert {urllib.parse.urlsplit(u).port for u in net} == {app_port}, net
    assert server.url.replace("http://", "ws://") + "/viser" in sockets, sockets
    assert viser_port != app_port
    assert not errors, errors
    page.close()
