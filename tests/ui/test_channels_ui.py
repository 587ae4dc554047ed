"""The dashboard follows the bench's channel count (issue 29 item 2), in a real appliance and
browser: a youBot run (9 channels: J1-J5 on 1-5, the wheels on 6-9) is announced with its count,
the Bench page plots nine encoders and PWMs, the Watch page lists enc1..enc9 (din1..din18) with
the wheels' counts moving once the base drives, and the run's 3D recording keeps all nine
encoders, so its replay moves the base. Then a RELbot run (one ico board) shows four again."""

from __future__ import annotations

from xrf_testing.harness import Server, wait_for
from xrf_testing.pages import dashboard_page

# The Watch page's table: every signal's name cell (pages/watch.js buildTable).
WATCH_NAMES = "[...document.querySelectorAll('#page-watch td')].map((td) => td.textContent)"


def test_a_youbot_run_shows_its_nine_channels_then_relbot_four(server: Server, browser) -> None:  # noqa: ANN001
    with dashboard_page(server, browser) as page:
        run = server.start_run("youbot")
        with server.ws() as ws:
            ws.wait_state("IDLE", 30)
            page.wait_for_function("window.xrf.run && window.xrf.run.channels === 9", timeout=30_000)
            keys = page.evaluate("xrf.plots.enc.keys.concat(xrf.plots.pwm.keys)")
            assert keys == [f"enc{i}" for i in range(1, 10)] + [f"pwm{i}" for i in range(1, 10)]
            ws.command("initialise")
            ws.wait_state("INITIALISED", 30)
            ws.command("start")
            ws.wait_state("RUN", 10)
            ws.send({"type": "setpoint", "fields": {"base_vx": 0.1}})
            # The wheels (channels 6-9) turn: their counts leave the value they had at rest.
            page.wait_for_function(
                "(() => { const e = xrf.lastTelemetry && xrf.lastTelemetry.enc;"
                " return e && e.length === 9 && e.slice(5).every((c) => c !== 0); })()",
                timeout=20_000,
            )
            page.goto(server.url + "/#watch")
            page.wait_for_function(f"{WATCH_NAMES}.includes('enc9')", timeout=10_000)
            names = page.evaluate(WATCH_NAMES)
            assert {"enc5", "enc9", "pwm9", "dout9", "din18"} <= set(names) and "enc10" not in names
            ws.send({"type": "setpoint", "fields": {"base_vx": 0.0}})
        server.stop_run()
        # The 3D recording holds all nine encoders: the replay drives the base forward.
        r = server.http.post("/api/viz/replay", json={"run_id": run["id"]})
        assert r.status_code == 200, r.text
        assert r.json()["kind"] == "youbot"
        end = r.json()["duration"]
        assert server.http.post("/api/viz/replay/seek", json={"t": end}).status_code == 200
        # The scene updates at 30 Hz while someone asks for its state: ask until it shows the end.
        state = wait_for(
            lambda: (
                (s := server.http.get("/api/viz/state").json()).get("mode") == "replay"
                and (s.get("pose") or {}).get("x", 0) > 0.01
                and s
            ),
            10,
            "the replay at its end, the base moved forward",
        )
        assert len(state["arm"]) == 5
        server.http.post("/api/viz/live")
        # A bench of one ico board: four channels again, on both pages.
        server.start_run("relbot")
        page.goto(server.url + "/")
        page.wait_for_function("window.xrf.run && window.xrf.run.channels === 4", timeout=30_000)
        assert page.evaluate("xrf.plots.enc.keys") == ["enc1", "enc2", "enc3", "enc4"]
        page.goto(server.url + "/#watch")
        page.wait_for_function(f"{WATCH_NAMES}.includes('enc4') && !{WATCH_NAMES}.includes('enc5')", timeout=10_000)
        assert "din8" in page.evaluate(WATCH_NAMES) and "din9" not in page.evaluate(WATCH_NAMES)
