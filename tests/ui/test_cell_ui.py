"""The production cell in a real appliance and browser (issue 29 item 4): the Bench page shows the
cell example's homed state (a badge from its Xeno2Ros `homed`: "not homed" before INITIALISING
finishes, "homed" after), `start` is refused while it homes, and the 3D view draws the cell,
homed on its switches from the live input pins."""

from __future__ import annotations

from xrf_testing.harness import Server
from xrf_testing.pages import dashboard_page


def test_bench_shows_the_cell_homing_and_the_3d_view_draws_it(server: Server, browser) -> None:  # noqa: ANN001
    with dashboard_page(server, browser) as page:
        # A project without `homed` shows no badge.
        assert page.is_hidden("#homed-badge")
        server.start_run("cell")
        with server.ws() as ws:
            ws.wait_state("IDLE", 30)
            page.wait_for_function("document.getElementById('homed-badge').textContent === 'not homed'", timeout=30_000)
            assert "bad" in page.get_attribute("#homed-badge", "class")
            ws.command("initialise")
            ws.wait_state("INITIALISED", 20)
        page.wait_for_function("document.getElementById('homed-badge').textContent === 'homed'", timeout=20_000)
        assert "ok" in page.get_attribute("#homed-badge", "class")
        # The 3D view: the cell's scene, every axis homed on its switch from the live pins.
        page.goto(server.url + "/#view3d")
        page.wait_for_function(
            "window.xrf.view3d && window.xrf.view3d.kind === 'cell' && window.xrf.view3d.mode === 'live'",
            timeout=30_000,
        )
        page.wait_for_function("window.xrf.view3d.homed && window.xrf.view3d.homed.every((h) => h)", timeout=20_000)
        state = server.http.get("/api/viz/state").json()
        assert state["kind"] == "cell" and len(state["axes"]) == 3
        # At the switch edges: each axis within a little travel of its zero.
        assert abs(state["axes"][0]) < 0.1 and abs(state["axes"][1]) < 0.005 and abs(state["axes"][2]) < 0.005, state
        page.wait_for_function("document.getElementById('v3d-values').textContent.includes('homed')")
