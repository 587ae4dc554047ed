"""The youBot in a real appliance and browser (issue 29 item 3): the Bench page shows the youBot
example's arm state (a badge from its Xeno2Ros `arm_ready`: "arm not ready" until INITIALISING
has raised the arm, "arm ready" after), and the 3D view draws the arm from the run's encoders,
raised to its ready pose."""

from __future__ import annotations

import math

from xrf_testing.harness import Server
from xrf_testing.pages import dashboard_page


def test_bench_shows_the_arm_ready_and_the_3d_view_draws_the_arm(server: Server, browser) -> None:  # noqa: ANN001
    with dashboard_page(server, browser) as page:
        assert page.is_hidden("#homed-badge")  # no run: no readiness field
        server.start_run("youbot")
        with server.ws() as ws:
            ws.wait_state("IDLE", 30)
            page.wait_for_function(
                "document.getElementById('homed-badge').textContent === 'arm not ready'", timeout=30_000
            )
            assert "bad" in page.get_attribute("#homed-badge", "class")
            ws.command("initialise")
            ws.wait_state("INITIALISED", 30)
        page.wait_for_function("document.getElementById('homed-badge').textContent === 'arm ready'", timeout=20_000)
        assert "ok" in page.get_attribute("#homed-badge", "class")
        assert "base" in page.get_attribute("#homed-badge", "title")
        # The 3D view: the youBot's scene, its arm at the ready pose from the live encoders.
        page.goto(server.url + "/#view3d")
        page.wait_for_function(
            "window.xrf.view3d && window.xrf.view3d.kind === 'youbot' && window.xrf.view3d.mode === 'live'",
            timeout=30_000,
        )
        page.wait_for_function("window.xrf.view3d.arm && window.xrf.view3d.arm[2] > 0.9", timeout=20_000)
        state = server.http.get("/api/viz/state").json()
        assert state["kind"] == "youbot" and len(state["arm"]) == 5
        ready = [0.0, math.radians(10), math.radians(60), math.radians(40)]
        assert all(abs(a - r) < math.radians(3) for a, r in zip(state["arm"], ready, strict=False)), state["arm"]
        page.wait_for_function("document.getElementById('v3d-values').textContent.includes('J3 ')")
