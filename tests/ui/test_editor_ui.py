"""The Editor and Watch pages in a real browser (Debian's chromium).

Editor: type a broken line into a project's file, save with Ctrl-S, the compiler's error appears as
a marker and an inline message at that line; fix it, "Build & run" reaches RUN running exactly the
build of the saved version; the history's diff shows the change, and the diff against the template
what the student wrote. Every request the page makes stays on the appliance.

Watch: a controller whose Xeno2Ros field is a 1 Hz sawtooth; the table's value changes while it
runs, Freeze stops the updates (telemetry still arriving), a trigger on the sawtooth crossing 0.5
upwards fires and freezes the capture around it, and a level it never reaches never fires.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from xrf_testing.harness import Server, shared_builds_root, start_server, stop_server, wait_for
from xrf_testing.projects_support import reachable_tmp

REPO = Path(__file__).resolve().parents[2]
SHOTS = REPO / "test-results"


@pytest.fixture(scope="module")
def server() -> Iterator[Server]:
    data = reachable_tmp("ui-editor")
    s = start_server(data, shared_builds_root())
    yield s
    stop_server(s)
    shutil.rmtree(data, ignore_errors=True)


def new_project(server, name: str) -> int:  # noqa: ANN001 (a Server or a logged-in client)
    http = server.http if isinstance(server, Server) else server
    r = http.post("/api/projects/from-template", json={"template": "base", "name": name})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def open_editor(page, server: Server, pid: int) -> None:  # noqa: ANN001
    page.goto(server.url + "/#editor")
    page.wait_for_function("window.xrfEditor && window.xrfEditor.cm")
    page.wait_for_selector(f"#ed-project option[value='{pid}']", state="attached")
    page.select_option("#ed-project", str(pid))
    page.wait_for_function(f"xrfEditor.pid === {pid} && xrfEditor.path === 'src/Template.cpp'")


def cm_line_of(page, text: str) -> int:  # noqa: ANN001
    """1-based line of the first line containing `text` in the editor."""
    n = page.evaluate(
        "(t) => { const cm = xrfEditor.cm; for (let i = 0; i < cm.lineCount(); i++)"
        " if (cm.getLine(i).includes(t)) return i + 1; return 0; }",
        text,
    )
    assert n, text
    return n


def test_edit_error_marker_fix_build_and_run(server: Server, browser) -> None:  # noqa: ANN001
    server.stop_run()
    pid = new_project(server, "ui_edit")
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    requests: list[str] = []
    page.on("request", lambda r: requests.append(r.url))
    open_editor(page, server, pid)
    assert page.evaluate("xrfEditor.cm.getOption('mode')") == "text/x-c++src"
    page.wait_for_selector(".CodeMirror .cm-keyword")  # highlighted as C++

    # Type a broken line after "int Template::run()" + "{", save with Ctrl-S.
    run_line = cm_line_of(page, "int Template::run()")
    page.evaluate(f"xrfEditor.cm.focus(); xrfEditor.cm.setCursor({{line: {run_line}, ch: 1}})")
    page.keyboard.press("Enter")
    page.keyboard.type("int oops = not_declared_anywhere;")
    bad_line = run_line + 2
    assert "not_declared_anywhere" in page.evaluate(f"xrfEditor.cm.getLine({bad_line - 1})")
    page.wait_for_selector("#ed-dirty:has-text('unsaved')")
    page.keyboard.press("Control+s")
    page.wait_for_selector(f".ed-marker.error[data-line='{bad_line}']", timeout=180_000)
    # the marker sits in that line's gutter, the message right under that line
    assert page.evaluate(f"!!xrfEditor.cm.lineInfo({bad_line - 1}).gutterMarkers['ed-diag-gutter']")
    inline = page.locator(f".ed-inline.error[data-line='{bad_line}']")
    assert "not_declared_anywhere" in inline.first.text_content()
    assert page.evaluate(f"xrfEditor.cm.lineInfo({bad_line - 1}).widgets.length") >= 1
    assert "failed" in page.text_content("#ed-status")
    SHOTS.mkdir(exist_ok=True)
    page.screenshot(path=str(SHOTS / "editor-error.png"))
    assert page.text_content("#ed-dirty") == ""

    # Fix it (the broken line out, a printed marker in), then one click: build and run.
    page.evaluate(f"""xrfEditor.cm.replaceRange('    monitor.printf("UI-EDIT-MARK\\\\n");\\n',
                      {{line: {bad_line - 1}, ch: 0}}, {{line: {bad_line}, ch: 0}})""")
    page.click("#ed-run")
    page.wait_for_function("xrf.state && xrf.state.active && xrf.state.name === 'RUN'", timeout=180_000)
    page.wait_for_selector("#ed-status:has-text('RUN')", timeout=10_000)
    assert page.locator(".ed-marker").count() == 0
    versions = server.http.get(f"/api/projects/{pid}/versions").json()
    assert [v["n"] for v in versions] == [3, 2, 1]
    bid = page.evaluate("xrfEditor.build.id")
    assert versions[0]["build"]["id"] == bid and versions[0]["build"]["status"] == "ok"
    run = server.http.get("/api/runs?limit=1").json()[0]
    assert run["build"] == f"project-{pid}-build-{bid}"
    page.wait_for_function("document.getElementById('monitor').textContent.includes('UI-EDIT-MARK')", timeout=15_000)

    # History: v3's diff (v2 -> v3) shows the fix; against the template, what the student wrote.
    page.click("#ed-versions li[data-n='3']")
    page.wait_for_selector(".ed-diff-file[data-path='src/Template.cpp']")
    adds = page.locator(".ed-diff .add").all_text_contents()
    dels = page.locator(".ed-diff .del").all_text_contents()
    assert any("UI-EDIT-MARK" in a for a in adds) and any("not_declared_anywhere" in d for d in dels)
    page.click("#ed-diff-template")
    page.wait_for_selector(".ed-diff-sum:has-text('template-base → v3')")
    assert page.locator(".ed-diff-file").count() == 1
    adds = page.locator(".ed-diff .add").all_text_contents()
    assert any("UI-EDIT-MARK" in a for a in adds)
    assert not page.locator(".ed-diff .del").all_text_contents()
    page.screenshot(path=str(SHOTS / "editor-diff.png"), full_page=True)
    server.stop_run()

    # Nothing the page loaded came from anywhere but the appliance (CodeMirror included).
    assert any("/static/vendor/codemirror/lib/codemirror.js" in u for u in requests)
    outside = [u for u in requests if not u.startswith(server.url) and not u.startswith(("data:", "blob:"))]
    assert not outside, outside
    page.close()


def test_unsaved_text_survives_a_refused_save(server: Server, browser) -> None:  # noqa: ANN001
    pid = new_project(server, "ui_conflict")
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    open_editor(page, server, pid)
    # Another tab saves the same file first.
    text = server.http.get(f"/api/projects/{pid}/files/src/Template.cpp").json()["content"]
    r = server.http.put(
        f"/api/projects/{pid}/files/src/Template.cpp",
        params={"base": 1, "build": "false"},
        content=(text + "// other tab\n").encode(),
    )
    assert r.status_code == 200
    page.evaluate("xrfEditor.cm.replaceRange('// mine\\n', {line: 0, ch: 0})")
    page.click("#ed-save")
    page.wait_for_selector("#ed-status.bad:has-text('changed since version 1')")
    assert page.evaluate("xrfEditor.cm.getLine(0)") == "// mine"  # the text stays
    assert page.text_content("#ed-dirty") != ""
    page.click("#ed-overwrite")
    page.wait_for_function("document.getElementById('ed-dirty').textContent === ''", timeout=180_000)
    got = server.http.get(f"/api/projects/{pid}/files/src/Template.cpp").json()
    assert got["version"] == 3 and got["content"].startswith("// mine\n")
    page.close()


def test_educator_reviews_a_students_project(server: Server, browser) -> None:  # noqa: ANN001
    pw = server.create_user("ui_ed_student")
    student, _ = server.login("ui_ed_student", pw)
    pid = new_project(student, "students_work")
    text = student.get(f"/api/projects/{pid}/files/src/main.cpp").json()["content"]
    assert (
        student.put(
            f"/api/projects/{pid}/files/src/main.cpp",
            params={"base": 1, "build": "false"},
            content=(text + "// by the student\n").encode(),
        ).status_code
        == 200
    )
    student.close()
    page = browser.new_page(viewport={"width": 1280, "height": 800})  # the harness's educator
    page.goto(server.url + "/#editor")
    page.wait_for_selector(f"#ed-project option[value='{pid}']:has-text('ui_ed_student')", state="attached")
    page.select_option("#ed-project", str(pid))
    page.wait_for_selector("#ed-versions li[data-n='2']")
    page.click("#ed-diff-template")
    page.wait_for_selector(".ed-diff-file[data-path='src/main.cpp']")
    assert any("by the student" in a for a in page.locator(".ed-diff .add").all_text_contents())
    page.close()


SAWTOOTH = (
    "xeno_msg.pos_left = ros_msg.steer_left;",
    "static long k = 0; k++; xeno_msg.pos_left = (k % 1000) / 1000.0;  // 1 Hz sawtooth 0..1",
)


def test_watch_values_freeze_and_trigger(server: Server, browser) -> None:  # noqa: ANN001
    server.stop_run()
    pid = new_project(server, "ui_watch")
    text = server.http.get(f"/api/projects/{pid}/files/src/Template.cpp").json()["content"]
    assert SAWTOOTH[0] in text
    s = server.http.put(
        f"/api/projects/{pid}/files/src/Template.cpp",
        params={"base": 1},
        content=text.replace(SAWTOOTH[0], SAWTOOTH[1]).encode(),
    ).json()
    bid = s["build"]["id"]
    wait_for(
        lambda: server.http.get(f"/api/projects/{pid}/builds/{bid}").json()["status"] in ("ok", "failed"),
        timeout=300,
        what="the build",
    )
    with server.ws() as ws:
        r = server.http.post(f"/api/projects/{pid}/builds/{bid}/run", json={}, timeout=60)
        assert r.status_code == 201, r.text
        ws.wait_state("IDLE", timeout=20)
        for cmd, state in (("initialise", "INITIALISED"), ("start", "RUN")):
            assert ws.command(cmd)["accepted"], cmd
            ws.wait_state(state)

    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.goto(server.url + "/#watch")
    page.wait_for_selector("#watch-row-x-pos_left")
    for row in (
        "x-pos_right",
        "r-steer_left",
        "r-steer_right",
        "enc1",
        "enc4",
        "pwm1",
        "pwm4",
        "din1",
        "din8",
        "dout1",
        "dout4",
    ):
        assert page.locator(f"#watch-row-{row}").count() == 1, row
    val = "document.querySelector('#watch-row-x-pos_left td.val').textContent"
    page.wait_for_function(f"{val} !== '–'", timeout=15_000)
    # nothing written yet: the controller's Ros2Xeno is zeros
    assert page.text_content("#watch-row-r-steer_left td.val") == "0"
    # the page fits the laptop's width (the scope sized from its column)
    wide = page.evaluate(
        "[...document.querySelectorAll('body *')].filter(e => e.getBoundingClientRect().right > window.innerWidth)"
        ".slice(0, 8).map(e => `${e.tagName}#${e.id}.${e.className} ${Math.round(e.getBoundingClientRect().right)}`)"
    )
    assert page.evaluate("document.documentElement.scrollWidth <= window.innerWidth"), wide
    # A scope left too wide by a layout change (no resize event comes) is fitted again.
    page.evaluate("xrfWatch.plot.setSize({width: 2000, height: 260})")
    page.wait_for_function("document.documentElement.scrollWidth <= window.innerWidth", timeout=5000)
    # The scope's column narrowed by the layout (as when the page's grid is applied after the plot
    # was built): refitted before the next paint, not at the next twice-a-second check.
    fits_after_two_frames = page.evaluate(
        """() => new Promise((done) => {
          const page = document.querySelector('.watch-page');
          const before = xrfWatch.plot.width;
          page.style.gridTemplateColumns = 'minmax(320px, 3fr) minmax(0, 2fr)';
          requestAnimationFrame(() => requestAnimationFrame(() => {
            const panel = document.getElementById('watch-scope-panel').getBoundingClientRect();
            const plot = document.querySelector('#watch-plot .uplot').getBoundingClientRect();
            page.style.gridTemplateColumns = '';
            done({ before, after: xrfWatch.plot.width, fits: plot.right <= panel.right });
          }));
        })"""
    )
    assert fits_after_two_frames["fits"] and fits_after_two_frames["after"] < fits_after_two_frames["before"], (
        fits_after_two_frames
    )
    page.wait_for_function("document.documentElement.scrollWidth <= window.innerWidth", timeout=5000)
    first = page.evaluate(val)
    # plotted by default: the run's Xeno2Ros fields
    assert page.evaluate("xrfWatch.plotKeys") == ["x.pos_left", "x.pos_right"]
    assert page.is_checked("#watch-row-x-pos_left input[type=checkbox]")
    page.wait_for_function(f"{val} !== {first!r}", timeout=30_000)  # changes while it runs

    # Freeze: the table and the scope stop, while telemetry keeps arriving.
    page.click("#watch-freeze")
    assert page.evaluate("xrfWatch.frozen")
    frozen_val, updates, shown = (
        page.evaluate(val),
        page.evaluate("xrfWatch.tableUpdates"),
        page.evaluate("xrfWatch.shown"),
    )
    count = page.evaluate("xrf.telemetryCount")
    page.wait_for_function(f"xrf.telemetryCount > {count + 10}", timeout=30_000)  # telemetry flows on
    assert page.evaluate(val) == frozen_val and page.evaluate("xrfWatch.tableUpdates") == updates
    assert page.evaluate("xrfWatch.shown") == shown
    page.click("#watch-freeze")  # resume
    page.wait_for_function(f"{val} !== {frozen_val!r}", timeout=5_000)

    # A level the sawtooth never reaches: armed, no trigger.
    page.select_option("#watch-window", "1")
    page.select_option("#watch-trig-signal", "x.pos_left")
    page.select_option("#watch-trig-edge", "rising")
    page.fill("#watch-trig-level", "2")
    page.click("#watch-arm")
    time.sleep(2.5)  # the point: a while (2.5 periods of the sawtooth) without a trigger
    assert page.evaluate("xrfWatch.triggered === null && !xrfWatch.frozen")
    assert "armed" in page.text_content("#watch-state")
    # 0.5 rising: crossed once a second; the capture freezes around it, t = 0 at the crossing.
    page.fill("#watch-trig-level", "0.5")
    page.click("#watch-arm")
    page.wait_for_function("xrfWatch.frozen && xrfWatch.triggered", timeout=10_000)
    trig = page.evaluate("xrfWatch.triggered")
    assert trig["key"] == "x.pos_left" and trig["before"] < 0.5 <= trig["after"], trig
    assert "triggered" in page.text_content("#watch-state")
    SHOTS.mkdir(exist_ok=True)
    page.screenshot(path=str(SHOTS / "watch-triggered.png"), full_page=True)
    shown = page.evaluate("xrfWatch.shown")
    assert shown["zero"] == trig["t"] and abs(shown["t0"] - (trig["t"] - 0.25)) < 1e-9 and shown["points"] > 10
    # the plotted samples cross 0.5 at x = 0: below just before, at or above just after
    xs, ys = page.evaluate("[xrfWatch.plot.data[0], xrfWatch.plot.data[1 + xrfWatch.plotKeys.indexOf('x.pos_left')]]")
    before = [y for x, y in zip(xs, ys) if -0.1 < x < 0]
    after = [y for x, y in zip(xs, ys) if 0 <= x < 0.1]
    assert before and after and max(before) < 0.5 <= min(after), (before, after)
    server.stop_run()
    page.close()
