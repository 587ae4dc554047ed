"""What the dashboard shows must be what is true now (issue 31, bugs 1, 2, 4, 5 and the scope):
the Watch page shows the Ros2Xeno the loop has, whoever wrote it; every command button is off,
saying why, for whoever may not use it; a deadline-miss alarm ends with its run and its holder;
a tab the role cannot use is not there; the scope scales each unit on its own axis and its
legend shows values without hovering. Real appliance, real loop, Debian's chromium.

Each test failed against the dashboard before its fix: XRF_TEST_FRONTEND=<folder> serves another
frontend (an older one exported with `git archive main frontend | tar -x -C <folder>/..`)."""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator

import pytest

from xrf_testing.harness import Server, browser_login, shared_builds_root, start_server, stop_server
from xrf_testing.projects_support import reachable_tmp

VIEW = {"width": 1280, "height": 900}
# How long the loop is stopped (SIGSTOP) to make it miss deadlines for real: tens of 1 kHz cycles,
# well under the appliance's hang limit (hang_timeout_ms, 200 ms).
STALL_S = 0.06


@pytest.fixture(scope="module")
def server() -> Iterator[Server]:
    extra = {"frontend_dir": os.environ["XRF_TEST_FRONTEND"]} if os.environ.get("XRF_TEST_FRONTEND") else {}
    s = start_server(reachable_tmp("ui31-data"), shared_builds_root(), **extra)
    yield s
    stop_server(s)


def state_is(page, name: str, timeout: float = 15_000) -> None:  # noqa: ANN001
    try:
        page.wait_for_function(f"document.getElementById('state-name').textContent === {name!r}", timeout=timeout)
    except Exception as exc:
        shown = page.evaluate("(document.getElementById('state-name') || {}).textContent")
        raise AssertionError(f"the page shows state {shown!r}, not {name!r}, at {page.url}") from exc


def command(http, cmd: str) -> None:  # noqa: ANN001
    r = http.post("/api/runs/current/command", json={"cmd": cmd})
    assert r.status_code == 200 and r.json()["accepted"], r.text


def watch_value(page, key: str) -> str:  # noqa: ANN001
    """The value cell of a Watch row (key "r.steer_left": the Ros2Xeno field steer_left)."""
    return page.inner_text(f"#watch-row-{key.replace('.', '-')} td.val")


def wait_watch(page, key: str, text: str, timeout: float = 10_000) -> None:  # noqa: ANN001
    row = f"watch-row-{key.replace('.', '-')}"
    page.wait_for_function(
        f"(document.querySelector('#{row} td.val') || {{}}).textContent === {text!r}", timeout=timeout
    )


def test_watch_shows_the_setpoints_the_loop_has(server: Server, browser) -> None:  # noqa: ANN001
    server.stop_run()
    server.start_run("relbot")
    for cmd in ("initialise", "start"):
        command(server.http, cmd)
    bench = browser.new_page(viewport=VIEW)  # one tab on the Bench page
    watch = browser.new_page(viewport=VIEW)  # another on Watch
    errors: list[str] = []
    for p in (bench, watch):
        p.on("pageerror", lambda e: errors.append(str(e)))
    bench.goto(server.url + "/")
    watch.goto(server.url + "/#watch")
    state_is(bench, "RUN", 60_000)
    wait_watch(watch, "r.steer_left", "0")

    # Changed on the Bench page of another tab: Watch shows it (it showed the old value).
    bench.fill("#sp-steer_left", "2.5")
    bench.fill("#sp-steer_right", "-1.25")
    wait_watch(watch, "r.steer_left", "2.5000")
    wait_watch(watch, "r.steer_right", "-1.2500")
    # The same tab's Watch, opened after the change, too.
    bench.goto(server.url + "/#watch")
    wait_watch(bench, "r.steer_left", "2.5000")
    wait_watch(bench, "r.steer_right", "-1.2500")

    # Written by another client altogether (a WebSocket of its own, as a CLI or another browser):
    # both tabs' Watch and the Bench page's controls follow the loop.
    bench.goto(server.url + "/#bench")
    bench.wait_for_function("document.getElementById('sp-steer_left').value === '2.5'")
    with server.ws() as ws:
        ws.send({"type": "setpoint", "fields": {"steer_right": 0.75}})
        assert ws.wait_type("ack", 10)["setpoint"]["steer_right"] == 0.75
        for p in (bench, watch):
            p.wait_for_function("document.getElementById('sp-steer_right').value === '0.75'")
        wait_watch(watch, "r.steer_right", "0.7500")
        wait_watch(watch, "r.steer_left", "2.5000")  # the other field is not taken back

        # A field the user is typing in is left alone; the loop's value comes when they leave it.
        bench.focus("#sp-steer_left")
        ws.send({"type": "setpoint", "fields": {"steer_left": -3}})
        assert ws.wait_type("ack", 10)["setpoint"]["steer_left"] == -3
        wait_watch(watch, "r.steer_left", "-3")
        bench.wait_for_function("xrf.lastTelemetry.ros2xeno.steer_left === -3")
        assert bench.input_value("#sp-steer_left") == "2.5"
        bench.focus("#sp-steer_right")
        bench.wait_for_function("document.getElementById('sp-steer_left').value === '-3'")
    # And the loop really has it: its Xeno2Ros position follows the setpoint.
    watch.wait_for_function("Math.abs(xrf.lastTelemetry.xeno2ros.pos_left + 3) < 0.1", timeout=15_000)
    assert not errors, errors
    bench.context.close()
    watch.context.close()
    server.stop_run()


def test_command_buttons_are_off_with_the_reason(server: Server, raw_browser, browser) -> None:  # noqa: ANN001
    server.stop_run()
    observer_pw = server.create_user("ui31-observer", "observer")
    student_pw = server.create_user("ui31-student", "student")
    assert server.http.post("/api/lease/take").status_code == 200  # the educator holds the bench
    server.start_run("relbot")
    for cmd in ("initialise", "start"):
        command(server.http, cmd)
    pages = {}
    for name, pw in (("ui31-observer", observer_pw), ("ui31-student", student_pw)):
        ctx = raw_browser.new_context(viewport=VIEW)
        pages[name] = ctx.new_page()
        browser_login(pages[name], server.url, name, pw)
    edu = browser.new_page(viewport=VIEW)
    edu.goto(server.url + "/")
    obs, stu = pages["ui31-observer"], pages["ui31-student"]
    for p in (obs, stu, edu):
        state_is(p, "RUN", 60_000)
        p.wait_for_function("document.getElementById('lease-holder').textContent !== '…'")

    # An observer: pause and stop (and STOP in the bar, Start and End run) are off, saying why.
    for sel in (
        "#commands [data-cmd=pause]",
        "#commands [data-cmd=stop]",
        "#btn-estop",
        "#btn-start-run",
        "#btn-end-run",
    ):
        obs.wait_for_function(f"document.querySelector({sel!r}).disabled")
        assert "watch only" in obs.get_attribute(sel, "title"), sel
    # A student without the bench: stop and pause are theirs (safety), the run's end is not.
    stu.wait_for_function("document.querySelector('#btn-end-run').disabled")
    assert stu.is_enabled("#commands [data-cmd=pause]") and stu.is_enabled("#commands [data-cmd=stop]")
    assert stu.is_enabled("#btn-estop")
    assert "holds the bench" in stu.get_attribute("#btn-end-run", "title")
    assert "holds the bench" in stu.get_attribute("#btn-start-run", "title")
    # Stopped: `reset` is off for the student (it was on and did nothing), on for the holder.
    command(server.http, "stop")
    for p in (obs, stu, edu):
        state_is(p, "STOPPED")
    stu.wait_for_function("document.querySelector('#commands [data-cmd=reset]').disabled")
    assert "holds the bench" in stu.get_attribute("#commands [data-cmd=reset]", "title")
    assert "not accepted in STOPPED" in stu.get_attribute("#commands [data-cmd=pause]", "title")
    edu.wait_for_function("!document.querySelector('#commands [data-cmd=reset]').disabled")
    assert edu.get_attribute("#commands [data-cmd=reset]", "title") == ""
    # The bench handed to the student: the same buttons come on for them.
    assert server.http.post("/api/lease/release").status_code == 200
    stu_http, _ = server.login("ui31-student", student_pw)
    try:
        assert stu_http.post("/api/lease/take").status_code == 200
        stu.wait_for_function("!document.querySelector('#commands [data-cmd=reset]').disabled")
        assert stu.is_enabled("#btn-end-run")
        stu.click("#commands [data-cmd=reset]")
        state_is(stu, "INITIALISED")
    finally:
        stu_http.post("/api/lease/release")
        stu_http.close()
    for p in (obs, stu, edu):
        p.context.close()
    server.stop_run()


def alarm_shown(page) -> bool:  # noqa: ANN001
    return page.evaluate("!document.getElementById('alarm').classList.contains('hidden')")


def miss_deadlines(pid: int) -> None:
    os.kill(pid, signal.SIGSTOP)
    try:
        time.sleep(STALL_S)  # the point: a stall the loop sees as missed deadlines
    finally:
        os.kill(pid, signal.SIGCONT)


def test_deadline_miss_alarm_ends_with_its_run_and_holder(server: Server, raw_browser, browser) -> None:  # noqa: ANN001
    server.stop_run()
    pw = server.create_user("ui31-holder", "student")
    http, _ = server.login("ui31-holder", pw)
    try:
        server.http.post("/api/lease/release")
        assert http.post("/api/lease/take").status_code == 200
        r = http.post("/api/runs", json={"build": "relbot"}, timeout=300)
        assert r.status_code == 201, r.text
        run = r.json()
        for cmd in ("initialise", "start"):
            command(http, cmd)
        ctx = raw_browser.new_context(viewport=VIEW)
        stu = ctx.new_page()
        browser_login(stu, server.url, "ui31-holder", pw)
        edu = browser.new_page(viewport=VIEW)
        edu.goto(server.url + "/")
        deadline_alarm = (
            "!document.getElementById('alarm').classList.contains('hidden')"
            " && document.getElementById('alarm').dataset.kind === 'deadline_miss'"
        )
        for p in (stu, edu):
            state_is(p, "RUN", 60_000)
        miss_deadlines(run["pid"])
        for p in (stu, edu):
            p.wait_for_function(deadline_alarm, timeout=15_000)

        # An educator takes the bench over: the holder changed, the alarm was the last holder's.
        # (Taken down, seen by an observer of the element: on a loaded machine this run's next
        # misses may put a new one up within the second, which is right: they are news.)
        for p in (stu, edu):
            p.evaluate(
                """() => { const box = document.getElementById('alarm'); window.__alarmDown = false;
                new MutationObserver(() => { if (box.classList.contains('hidden')) window.__alarmDown = true; })
                  .observe(box, {attributes: true}); }"""
            )
        assert server.http.post("/api/lease/take").json()["holder"]["username"] != "ui31-holder"
        for p in (stu, edu):
            p.wait_for_function("window.__alarmDown === true")

        # Misses again, then the run ends: its alarm goes with it.
        miss_deadlines(run["pid"])
        edu.wait_for_function(deadline_alarm, timeout=15_000)
        server.stop_run()
        for p in (stu, edu):
            p.wait_for_function("/ended/.test(document.getElementById('run-detail').textContent)")
            p.wait_for_function("document.getElementById('alarm').classList.contains('hidden')")
        # (and a late one of the ended run does not bring it back)
        edu.evaluate(
            f"xrf.handlers.alarm({{type: 'alarm', kind: 'deadline_miss', run_id: {run['id']}, message: 'late'}})"
        )
        assert not alarm_shown(edu)
        ctx.close()
        edu.context.close()
    finally:
        server.http.post("/api/lease/release")
        http.close()


def test_tabs_only_for_what_the_role_may_do(server: Server, raw_browser) -> None:  # noqa: ANN001
    pages = {}
    for name, role in (("ui31-obs-tabs", "observer"), ("ui31-stu-tabs", "student")):
        pw = server.create_user(name, role)
        pages[role] = raw_browser.new_context(viewport=VIEW).new_page()
        browser_login(pages[role], server.url, name, pw)
    obs, stu = pages["observer"], pages["student"]
    stu.wait_for_selector("#nav a[data-page=projects]")
    assert stu.is_visible("#nav a[data-page=editor]")
    obs.wait_for_selector("#nav a[data-page=watch]")
    tabs = obs.eval_on_selector_all("#nav a", "as => as.map(a => a.dataset.page)")
    assert "projects" not in tabs and "editor" not in tabs, tabs
    assert "runs" in tabs and "bench" in tabs, tabs
    # Their addresses show the Bench, not a page that can only refuse.
    obs.goto(server.url + "/#projects")
    obs.wait_for_function("!document.getElementById('page-bench').classList.contains('hidden')")
    assert obs.evaluate(
        "!document.getElementById('page-projects') || document.getElementById('page-projects').classList.contains('hidden')"
    )
    for p in (obs, stu):
        p.context.close()


def test_scope_scales_each_unit_and_legends_show_values(server: Server, browser) -> None:  # noqa: ANN001
    server.stop_run()
    server.start_run("relbot")
    for cmd in ("initialise", "start"):
        command(server.http, cmd)
    page = browser.new_page(viewport=VIEW)
    page.goto(server.url + "/#watch")
    state_is(page, "RUN", 60_000)
    page.wait_for_selector("#watch-row-x-pos_left input")
    with server.ws() as ws:
        ws.send({"type": "setpoint", "fields": {"steer_left": 1.5}})
        assert ws.wait_type("ack", 10)["setpoint"]["steer_left"] == 1.5
    # pos_left (rad, ticked by default) beside enc1 (counts, thousands)
    page.check("#watch-row-enc1 input")
    page.wait_for_function("xrfWatch.plotKeys.includes('enc1') && xrfWatch.plotKeys.includes('x.pos_left')")
    page.wait_for_function("Math.abs(xrf.lastTelemetry.xeno2ros.pos_left - 1.5) < 0.1", timeout=15_000)
    page.wait_for_function("xrfWatch.shown && xrfWatch.shown.points > 10")
    scales = page.evaluate(
        """() => {
          const u = xrfWatch.plot, out = {};
          // The newest value the plot holds, read with its scale: the signal keeps moving, and a
          // value read later (xrfWatch.values) may be past the scale of the last redraw.
          u.series.forEach((s, i) => {
            if (i) out[s.label] = [s.scale, u.scales[s.scale].min, u.scales[s.scale].max, u.data[i].at(-1)];
          });
          return out;
        }"""
    )
    pos, enc = scales["pos_left"], scales["enc1"]
    assert pos[0] != enc[0], scales  # not one axis
    # Each fits its own signal: the position's range is a few rad, not the counts' thousands.
    assert pos[2] - pos[1] < 10 and pos[1] <= 1.5 <= pos[2], scales
    assert enc[3] is not None and enc[1] <= enc[3] <= enc[2], scales
    # Both axes drawn: one per unit, the counts' labelled.
    assert page.evaluate("xrfWatch.plot.axes.filter(a => a.show !== false).length") >= 3  # x + two y
    # Legends show the current values without hovering, on Watch and on the Bench page.
    page.mouse.move(5, 5)
    values = page.eval_on_selector_all(
        "#watch-plot .u-legend .u-series:not(:first-child) .u-value", "els => els.map(e => e.textContent)"
    )
    assert values and all(v not in ("--", "") for v in values), values
    page.goto(server.url + "/#bench")
    page.wait_for_function("window.xrf.plots.enc.data[0].length > 5")
    page.wait_for_function(
        "[...document.querySelectorAll('#plot-enc .u-legend .u-series:not(:first-child) .u-value')]"
        ".every(e => e.textContent !== '--' && e.textContent !== '')"
    )
    page.context.close()
    server.stop_run()
