"""The 3D view does no work for nobody (issue 30 item 4): with no viser client connected and
nobody polling /api/viz/state, the scene's updater sleeps (no frames are sent); a client
connecting through the appliance's /viser/ proxy wakes it, and it sleeps again when the client
leaves. GET /api/viz (info) is what this test reads: it does not count as watching."""

from __future__ import annotations

import time

import viser
from websockets.sync.client import connect
from websockets.typing import Subprotocol

from xrf_testing.harness import Server, wait_for


def info(server: Server) -> dict:
    return server.http.get("/api/viz").json()


def frames_stay(server: Server) -> int:
    """The frame count, checked not to move while nobody watches."""
    wait_for(lambda: not info(server)["watched"], 20, "nobody watching the 3D view")
    before = info(server)["frames"]
    time.sleep(0.5)  # time passing: 15 periods of the 30 Hz updater, none of which may send a frame
    after = info(server)
    assert not after["watched"] and after["frames"] == before, (before, after)
    return before


def test_viser_starts_at_the_first_watcher(server: Server) -> None:
    """viser (its import and server: ~25 MB RSS and threads in the appliance) is not started with
    the appliance but by the first request through the /viser/ proxy."""
    before = info(server)
    assert before["available"] and not before["started"] and before["port"] is None, before
    assert server.http.get("/viser/").status_code == 200
    after = info(server)
    assert after["started"] and after["port"], after


def test_the_scene_sleeps_with_no_viewer_and_wakes_for_one(server: Server) -> None:
    assert info(server)["available"], info(server)
    idle = frames_stay(server)
    ws_url = server.url.replace("http://", "ws://") + "/viser"
    cookie = {"Cookie": f"xrf_session={server.http.cookies.get('xrf_session')}"}
    proto = Subprotocol(f"viser-v{viser.__version__}")
    with connect(ws_url, subprotocols=[proto], origin=server.url, additional_headers=cookie, max_size=None) as ws:
        ws.recv(timeout=10)  # viser's first scene messages: the client is connected
        wait_for(lambda: info(server)["watched"] and info(server)["frames"] > idle + 3, 20, "the scene updating")
    # The client left: the updater goes back to sleep.
    frames_stay(server)


def test_polling_the_state_keeps_it_updating(server: Server) -> None:
    """An API user (or the 3D page) polling /api/viz/state sees a scene that updates."""
    idle = frames_stay(server)
    first = server.http.get("/api/viz/state").json()
    assert first["watched"]
    wait_for(
        lambda: server.http.get("/api/viz/state").json()["frame"] > max(idle, first.get("frame", 0)), 20, "a new frame"
    )
