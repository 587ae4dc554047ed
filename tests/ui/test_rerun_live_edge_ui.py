"""The live rerun viewer, opened mid-run in chromium, starts at the live edge (issue 31 bug 6).

Before: the run's proxy replayed its whole buffer (256 MiB) oldest first, and a viewer opened four
minutes into a run drew cycle 0 onwards for two minutes ("216.6 s latency", counting down) before it
reached the loop. Now the proxy keeps a short window and sends it newest first
(logs/rerun_servers.py LiveProxy), and the tab offers the replay from the run's start as its log's
.rrd (frontend/rerun-tab.js). Measured in the browser, from the viewer's own state
(``window._handle.viewer_state()``: the oldest and newest sample of the run it holds; its following
plots end at the newest), not at the wire.

What a frame draws is bounded (issue 31 bug 6, continued: chromium without a GPU driver redraws
about once a second at 1280x800): the live stream is min/max-decimated to a display rate
(tests/logs/test_live_decimation.py), each plot shows its last seconds, and the live view's canvas
is smaller than the tab unless the viewer asks for full size; the page says that the live view is
decimated and where every sample is. How far behind live that keeps the viewer is a figure of
bench/appliance/rerun_lag.py, not asserted here (timing belongs in benchmarks).

At the live edge from the first second (issue 31 bug 6, continued): serving a live viewer's page
makes the run's recording stream before the viewer's app has started (logs/rerun_servers.py
LiveProxy.expect_viewer), so the proxy replays the live edge when the viewer connects; and in the
live tab the viewer draws a frame when the stream brought data, on input, and otherwise at most
twice a second (frontend/rerun-tab.js), not every frame: without a GPU driver each frame costs the
browser's GPU process ~0.3 CPU-seconds.

From the page's load (issue 31 bug 6, continued): the tab script asks for the live stream as the
viewer's wasm is compiled (session 10: at the page's load before, which queued the stream's first
seconds in the response, oldest first) and hands that response to the viewer when its app asks
(one request), it starts the viewer's wasm compiling from its fetch at once, and a line over the
canvas says what the tab is doing ("starting the viewer…", "connecting to the live stream…")
until the viewer holds a sample of the run. Asserted here with the wasm held back (so without
timing): the line is there before the viewer's app exists and the stream not yet asked for, the
viewer reads one stream, and the line goes once it holds the run's samples. The first viewer of a
run opened from the Runs page, as a person does: the first test. How soon (seconds after the
opening) is a figure of bench/appliance/rerun_lag.py.

Every opening (session 11): what the early response brought before the viewer asked is handed over
newest first, so a viewer whose app starts late draws the latest batch first, not what was newest
when the tab connected; and the line is there while the viewer's own script still loads.

Off the page's thread (session 13): the early response is read in a worker, each batch when it
comes, so what came while the page's thread was busy (the viewer's start) is still handed over
newest first: the page kept busy from the tab's request on, the first of the run's samples handed
to the viewer is from the newest batch, not the proxy's window from when the page went busy.
"""

from __future__ import annotations

import itertools
import time
import urllib.parse
from collections.abc import Iterator
from pathlib import Path

from xrf_testing.grpcweb import EMPTY_REQUEST, GRPC_WEB, READ_MESSAGES, split_frames
from xrf_testing.harness import Server, wait_for
from xrf_testing.rerun_stream import (
    STORE_RECORDING,
    chunk_of,
    viewer_active,
    viewer_newest_ns,
    viewer_oldest_ns,
    viewer_recordings,
    viewer_time_range,
)

# The run streams this long before the viewer opens: the old replay started this far behind. Three
# times EDGE_S is enough to tell a replay from cycle 0 from the live edge (40 s made this the
# suite's slowest test, for nothing more).
LATE_S = 15.0
# Nobody watched the run before this viewer, so its stream starts with it (logs/rerun_live.py) and
# the proxy keeps only a short window anyway (rerun_servers.LIVE_WINDOW: ~2 s of RELbot): the
# oldest sample the viewer holds is at most that window older than its opening (a replay from
# cycle 0 would start LATE_S older). A bound from what the stream does, not from how fast the
# browser draws: on a loaded machine with a software GPU the viewer's thread stalls for seconds
# (bench/appliance/README.md).
WINDOW_S = 2.0
# The newest sample of the first frame with data is at most this much older than the opening: the
# recording starts with the viewer's page, so what the proxy hands over first is newer than that,
# however slowly the browser draws (slowness only makes it newer).
EDGE_S = 1.0
# How long after the viewer's app started it may take to hold a sample newer than its opening (a
# time-out for a wait, generous: the first frame with data takes seconds on a loaded 2-core VM).
FIRST_S = 60.0
# The live view's canvas by default (frontend/rerun-tab.js LIVE_CANVAS), in CSS px (= device px here).
LIVE_CANVAS_WIDTH = 800

# The viewer's wasm is held back this long after the page was served (the test's route), and the
# test reads the stream itself meanwhile: samples older than its connection are there only because
# the page's load started the recording (expect_viewer); without that nothing is sent before a
# reader connects, and the records drained at its connection are at most a drain period (< 0.5 s)
# older. The proxy's window holds ~1.5 s of RELbot (rerun_servers.LIVE_WINDOW): PRE_S is inside it.
PAGE_AHEAD_S = 6.0
PRE_S = 1.0
READ_CHUNKS = 40  # chunks with samples the test reads: more than the window's (newest first)

# console.debug lines the viewer's tab may print while it starts and draws its first plots: rerun's
# web build logs its shader compiler (naga) at debug level, ~9000 lines at the first plot.
MAX_DEBUG_LINES = 20

# In the viewer's tab: its state every 250 ms, with the browser's wall clock (same machine).
SAMPLE = """window._xrfSamples = []; setInterval(() => {
  try { window._xrfSamples.push([Date.now(), Array.from(window._handle.viewer_state())]); } catch (e) {}
}, 250);"""


# Asks for a frame as the viewer does (unless one is held already); answers how many are held.
ASK_FRAME = """(() => {
  if (xrfRerunTab.frames().held === 0) requestAnimationFrame(() => {});
  return xrfRerunTab.frames().held;
})()"""


# In the viewer's tab (not the dashboard's), before its own scripts: the viewer's state at the end of
# each frame (the frame that ingests a sample draws it) and whether the tab's start-up line was on
# screen then, kept when either changed.
FRAME_STATES = """if (location.pathname.startsWith("/rerun/")) (() => {
  window._xrfFrameStates = [];
  let handle, last = "";
  Object.defineProperty(window, "_handle", { configurable: true, get: () => handle, set: (v) => { handle = v; } });
  const raf = window.requestAnimationFrame.bind(window);
  window.requestAnimationFrame = (cb) => raf((t) => {
    cb(t);
    if (!handle || window._xrfFrameStates.length > 2000) return;
    let st;
    try { st = Array.from(handle.viewer_state()); } catch (e) { return; }
    const line = document.getElementById("xrf-live-status");
    const shown = !!line && getComputedStyle(line).display !== "none";
    const key = st.join(",") + shown;
    if (key !== last) { last = key; window._xrfFrameStates.push([Date.now(), st, shown]); }
  });
})();"""


def _rerun_loaded(pid: int) -> bool:
    """rerun's native library is mapped in process `pid` (the SDK was imported: never, in the appliance)."""
    return "rerun_bindings" in Path(f"/proc/{pid}/maps").read_text()


def _sample_times(server: Server) -> Iterator[int]:
    """The newest sample (wall ns) of each chunk of the run's recording that a headless reader of
    the live stream is handed (gRPC-web through the appliance, as the viewer reads), in the order
    they come; the stream is closed when the caller stops taking them."""
    with server.http.stream("POST", READ_MESSAGES, content=EMPTY_REQUEST, headers=GRPC_WEB, timeout=60) as r:
        assert r.status_code == 200, r.headers
        rest = b""
        for raw in r.iter_raw():
            got, rest = split_frames(rest + raw)
            for flag, payload in got:
                chunk = chunk_of(payload) if flag == 0 else None
                if chunk is not None and chunk.store_kind == STORE_RECORDING and chunk.newest_time_ns is not None:
                    yield chunk.newest_time_ns


def test_the_first_viewer_of_a_run_opened_from_the_runs_page_starts_at_the_live_edge(
    server: Server,
    browser,  # noqa: ANN001
) -> None:
    """As a person opens it: the Runs page during a run nobody has watched, its "Live plots" button,
    the viewer in a tab of its own. The first frame the viewer draws with the run's data holds only
    the last seconds before the opening (the live edge, newest first), never the run from cycle 0
    (it is LATE_S old); until that frame the tab's line says what it is doing (no empty plots
    without a word); the replay from the run's start is offered beside it, as its log's .rrd in a
    tab of its own. And the appliance never loads the rerun SDK, not even for the viewer it streams
    to (logs/rerun_sender.py; issue 30 item 4). How soon the first sample comes is a figure of
    bench/appliance/rerun_lag.py --via-runs-page (no timing asserted here)."""
    server.stop_run()
    pid = server.proc.pid
    warm = browser.new_page(viewport={"width": 1280, "height": 800})
    # The viewer's files are prepared on the first visit (a child process gzips 43 MB of wasm):
    # not part of what is looked at here.
    warm.goto(server.url + "/rerun/index.html", timeout=600_000)
    warm.wait_for_function("() => window._handle !== undefined", timeout=300_000)
    warm.close()
    # (this module's first test: nothing in it has watched a run live yet)
    assert not _rerun_loaded(pid), "rerun was imported in the appliance"

    run = server.start_run("relbot")
    with server.ws() as ws:
        ws.to_run()
    started = time.monotonic()
    dash = browser.new_page(viewport={"width": 1280, "height": 800})
    dash.context.add_init_script(FRAME_STATES)
    dash.goto(server.url + "/#watch")
    wait_for(lambda: time.monotonic() - started >= LATE_S, LATE_S + 5, "the run's age")  # the run's age, on purpose
    # A dashboard on another of its pages, the run live all along: rerun stays out of the appliance.
    assert not _rerun_loaded(pid), "a dashboard's page made the appliance import rerun"
    dash.goto(server.url + "/#runs")
    dash.wait_for_selector("#rr-live", state="visible", timeout=60_000)
    with dash.context.expect_page(timeout=120_000) as popup:
        opened_ns = time.time_ns()
        dash.click("#rr-live")
    viewer = popup.value
    viewer.wait_for_function("() => window._handle !== undefined", timeout=300_000)
    recording = f"run-{run['id']}"

    def first_drawn() -> tuple[int, int, list[bool]] | None:
        states = viewer.evaluate("window._xrfFrameStates")
        for i, (_, state, _) in enumerate(states):
            oldest, newest = viewer_time_range(bytes(state), recording)
            if newest is not None and oldest is not None:
                return oldest, newest, [shown for _, _, shown in states[:i]]
        return None

    oldest, newest, line_before = wait_for(first_drawn, FIRST_S, "the viewer's first frame with the run's samples")
    # The live edge: the samples of its first frame with data are from the last seconds before the
    # opening or after it (the recording starts with the viewer's page), not the run from its start.
    assert (opened_ns - oldest) / 1e9 <= WINDOW_S, (
        f"the viewer's first frame with data held samples {(opened_ns - oldest) / 1e9:.1f} s older than its "
        f"opening (the run was {LATE_S:.0f} s old): a replay, not the live edge"
    )
    assert (opened_ns - newest) / 1e9 <= EDGE_S, (
        f"the newest sample of the viewer's first frame with data was {(opened_ns - newest) / 1e9:.1f} s older "
        "than its opening"
    )
    assert not _rerun_loaded(pid), "the appliance imported rerun to stream to a viewer"
    # Until that frame, the tab said what it was doing (its line over the canvas)...
    assert line_before and all(line_before), line_before
    # ...and the line goes once the first sample is drawn.
    wait_for(
        lambda: viewer.evaluate("document.getElementById('xrf-live-status').dataset.step") == "shown",
        30,
        "the start-up line to go once the viewer drew a sample",
    )

    # The replay from the run's start: separate, a link to the run's log as .rrd in a viewer tab of
    # its own; this tab stays the live stream.
    viewer.wait_for_function("document.getElementById('xrf-replay') !== null", timeout=30_000)
    link = viewer.eval_on_selector("#xrf-replay", "a => [a.href, a.target, a.textContent]")
    href, target, text = link
    replay = urllib.parse.parse_qs(urllib.parse.urlsplit(href).query)["url"][0]
    assert target == "_blank" and f"run {run['id']} from its start" in text, link
    assert replay.startswith(f"{server.url}/api/logs/viewer/") and replay.endswith(".rrd"), href
    live = urllib.parse.parse_qs(urllib.parse.urlsplit(viewer.url).query)["url"][0]
    assert live.endswith("/proxy") and live != replay, viewer.url
    rrd = server.http.get(replay.removeprefix(server.url))
    assert rrd.status_code == 200 and rrd.content[:4] == b"RRF2", rrd.content[:8]
    viewer.close()
    dash.close()
    server.stop_run()


def _live_run_with_the_viewer_prepared(server: Server, browser) -> tuple[dict, dict]:  # noqa: ANN001
    """A RELbot run in RUN with its live stream up, the viewer's files prepared first (on the first
    visit a child process gzips 43 MB of wasm: not part of what the tests look at): (the run, the
    appliance's /api/logs/rerun answer)."""
    server.stop_run()
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.goto(server.url + "/rerun/index.html", timeout=600_000)
    page.wait_for_function("() => window._handle !== undefined", timeout=300_000)
    page.close()
    run = server.start_run("relbot")
    with server.ws() as ws:
        ws.to_run()
    info = wait_for(
        lambda: (i := server.http.get("/api/logs/rerun").json())["live_run"] == run["id"] and i, 30, "the live stream"
    )
    return run, info


def test_a_late_viewer_opens_at_the_live_edge(server: Server, browser) -> None:  # noqa: ANN001
    run, info = _live_run_with_the_viewer_prepared(server, browser)
    started = time.monotonic()
    wait_for(lambda: time.monotonic() - started >= LATE_S, LATE_S + 5, "the run's age")  # the run's age, on purpose

    viewer = browser.new_page(viewport={"width": 1280, "height": 800})
    debug_lines: list[str] = []
    viewer.on("console", lambda m: m.type == "debug" and debug_lines.append(m.text))
    stream_requests: list[str] = []
    viewer.on("request", lambda r: r.url.endswith(READ_MESSAGES) and stream_requests.append(r.url))
    # The viewer's wasm is held back until the test lets it go: until then its app cannot start.
    wasm_held: list = []
    viewer.route("**/rerun/re_viewer_bg.wasm", lambda route: wasm_held.append(route))
    opened, opened_ns = time.monotonic(), time.time_ns()
    viewer.goto(
        server.url + "/rerun/?url=" + urllib.parse.quote(info["live_url"], safe=""),
        wait_until="commit",
        timeout=120_000,
    )
    wait_for(lambda: time.monotonic() - opened >= PAGE_AHEAD_S, PAGE_AHEAD_S + 5, "the page's head start")  # on purpose
    # (route handlers run inside Playwright calls: the evaluate lets the wasm's request reach the list)
    wait_for(lambda: viewer.evaluate("0") == 0 and wasm_held, 60, "the page to ask for the viewer's wasm")
    # Before the viewer's app exists, the page says what it is doing (not empty plots), and the
    # live stream is not asked for yet: the tab script asks once the viewer's wasm is compiled, just
    # ahead of the viewer (frontend/rerun-tab.js: asked at the page's load, the stream's data queued
    # in the response in the order it came and the viewer's first frames drew its oldest).
    # (the wasm is asked for by the tab script's first lines; the line is drawn once the body is
    # parsed: on a loaded machine that can come after)
    status = wait_for(
        lambda: viewer.evaluate(
            "(() => { const b = document.getElementById('xrf-live-status'); return b && [b.dataset.step, b.textContent]; })()"
        ),
        30,
        "the page's status line",
    )
    assert status is not None and status[0] == "loading" and "loading the viewer" in status[1], status
    tab = viewer.evaluate("xrfRerunTab.frames()")
    assert tab["early"] == "none" and tab["streamAt"] is None and tab["viewerAskedAt"] is None, tab
    assert not stream_requests, stream_requests
    # While its wasm is held back, the page's load has started the run's stream: a reader that
    # connects now is handed samples from before it connected (the proxy's window, newest first),
    # not only what comes after (as when nothing is sent before a viewer reads).
    connect_ns = time.time_ns()
    older_than_connect = [(connect_ns - t) / 1e9 for t in itertools.islice(_sample_times(server), READ_CHUNKS)]
    assert max(older_than_connect) >= PRE_S, (
        f"a reader connecting {PAGE_AHEAD_S:g} s after the live page was served got samples at most "
        f"{max(older_than_connect):.2f} s older than its connection: nothing was streamed while the page loaded"
    )

    wasm_held[0].continue_()
    viewer.wait_for_function("() => window._handle !== undefined", timeout=300_000)
    viewer.evaluate(SAMPLE)
    recording = f"run-{run['id']}"

    first_oldest: list[int] = []  # the oldest sample it held when it first held any

    def newer_than_opening() -> tuple[float, int, int] | None:
        for t_ms, state in viewer.evaluate("window._xrfSamples.splice(0)"):
            newest = viewer_newest_ns(bytes(state), recording)
            oldest = viewer_oldest_ns(bytes(state), recording)
            if newest is None or oldest is None:
                continue
            if not first_oldest:
                first_oldest.append(oldest)
            if newest > opened_ns:
                return t_ms / 1000, newest, oldest
        return None

    seen_s, newest, oldest = wait_for(newer_than_opening, FIRST_S, "the viewer to hold a sample newer than its opening")
    # From its first data on, nothing older than the live window: not a replay of the run from its start.
    older = (opened_ns - min(first_oldest[0], oldest)) / 1e9
    assert older <= WINDOW_S, (
        f"the viewer held samples {older:.1f} s older than its opening (the run was {LATE_S:.0f} s old); "
        f"{seen_s - newest / 1e9:.1f} s behind live when its thread showed them"
    )

    # The viewer read one stream: the one the tab script asked for once the wasm was compiled, handed
    # to it ("used"),
    # and the line over the canvas went once it drew the stream's data.
    tab = viewer.evaluate("xrfRerunTab.frames()")
    assert tab["early"] == "used" and tab["viewerAskedAt"] is not None, tab
    assert tab["firstDataAt"] is not None, tab
    assert len(stream_requests) == 1, stream_requests
    wait_for(
        lambda: viewer.evaluate("document.getElementById('xrf-live-status').dataset.step") == "shown",
        30,
        "the start-up line to go once the viewer drew data",
    )
    assert viewer.evaluate("getComputedStyle(document.getElementById('xrf-live-status')).display") == "none"

    # Its first plots drew without the shader compiler's ~9000 console.debug lines, which froze the
    # tab for seconds (the tab script mutes console.debug there; ours, frontend/rerun-tab.js).
    assert len(debug_lines) <= MAX_DEBUG_LINES, (len(debug_lines), debug_lines[:5])

    # The run's replay from its start is one click away, as its log's .rrd.
    viewer.wait_for_function("document.getElementById('xrf-replay') !== null", timeout=30_000)
    href = viewer.get_attribute("#xrf-replay", "href")
    target = urllib.parse.parse_qs(urllib.parse.urlsplit(href).query)["url"][0]
    assert target.startswith(f"{server.url}/api/logs/viewer/") and target.endswith(".rrd"), href
    rrd = server.http.get(target.removeprefix(server.url))
    assert rrd.status_code == 200 and rrd.content[:4] == b"RRF2", rrd.content[:8]
    # ...and the page says the live view is decimated and where every sample is (figures from the API).
    note = viewer.text_content("#xrf-live-note")
    assert "points/s per signal" in note and "Every sample is in the run's log" in note, note
    assert f"{info['live_points_per_s']:g} points/s" in note and f"last {info['live_span_s']:g} s" in note, note

    # The live canvas is smaller than the tab by default (fewer pixels for a software renderer to
    # draw); "Full-size view" gives the whole tab, and the viewer resizes its pixels to it.
    size = "(() => { const c = document.getElementById('the_canvas_id'); return [c.width, c.height]; })()"
    width, height = viewer.evaluate(size)
    assert 0 < width <= LIVE_CANVAS_WIDTH and height < 800, (width, height)
    viewer.click("#xrf-canvas-toggle")
    viewer.wait_for_function("document.getElementById('the_canvas_id').width === 1280", timeout=60_000)

    # Frames on demand: once the stream is quiet (the run ended), a frame asked for is held, not
    # drawn at the browser's rate...
    server.stop_run()
    wait_for(lambda: viewer.evaluate(ASK_FRAME) > 0, 60, "a frame held while the stream brings nothing")
    # ...still drawn within half a second or so (the viewer's own animations, its latency readout)...
    viewer.evaluate("window._xrfDrawn = false; requestAnimationFrame(() => { window._xrfDrawn = true; })")
    # Polled from here: the viewer's CSP has no 'unsafe-eval', which Playwright's interval polling of
    # a page-side predicate needs (its rAF polling would itself wait on the gated frames).
    wait_for(lambda: viewer.evaluate("window._xrfDrawn === true"), 30, "the held frame drawn")
    # ...and at once after mouse or keyboard input (in the same task: no time passes in between).
    after_input = viewer.evaluate(
        "(() => { window.dispatchEvent(new PointerEvent('pointermove')); const a = xrfRerunTab.frames().held; "
        "requestAnimationFrame(() => {}); return [a, xrfRerunTab.frames().held]; })()"
    )
    assert after_input == [0, 0], after_input
    viewer.close()


# How long nobody watches before a viewer comes back: the recording sends only while watched, so
# the proxy's window is then at least this old. Twice a margin for the first reader's leaving to be
# noticed (at the next batch, 0.5 s) and the recording's last round.
PAUSE_S = 4.0


def _first_sample_ns(server: Server) -> int:
    """The newest sample of the first chunk with samples a headless reader is handed."""
    first = next(_sample_times(server), None)
    assert first is not None, "the live stream ended before any sample"
    return first


def test_a_viewer_back_after_a_pause_is_handed_the_live_edge_first(server: Server) -> None:
    """Nobody watched for a while, then a viewer connects: the run's recording had stopped sending
    (it sends only while watched), so the proxy's window is what it sent before the pause, and it
    replays that first, newest first: a viewer reopened minutes later drew minutes-old samples
    before the live ones. The read route now waits until the recording has sent again
    (LiveProxy.fresh), so the first sample handed over is newer than the pause's start."""
    server.stop_run()
    run = server.start_run("relbot")
    with server.ws() as ws:
        ws.to_run()
    wait_for(lambda: server.http.get("/api/logs/rerun").json()["live_run"] == run["id"], 30, "the live stream")
    _first_sample_ns(server)  # a viewer watches, then leaves
    left_ns, left = time.time_ns(), time.monotonic()
    wait_for(lambda: time.monotonic() - left >= PAUSE_S, PAUSE_S + 5, "the pause")  # nobody watches, on purpose
    first = _first_sample_ns(server)
    assert first > left_ns + PAUSE_S / 2 * 1e9, (
        f"a viewer back {PAUSE_S:g} s after the last one left was first handed a sample from "
        f"{(first - left_ns) / 1e9:+.2f} s after that: the window from before the pause"
    )
    server.stop_run()


# The viewer's app is held back this long after the tab script asked for the live stream (the
# viewer's JavaScript, re_viewer.js, held by the test's route): the stream's data waits in that
# early response meanwhile, a person's browser starting slowly (a loaded machine: the app started
# 1.2-6 s after the opening, bench/README.md). Its newest batch must be what the viewer's first
# frame holds, not the proxy's window from the connection HOLD_S before.
HOLD_S = 8.0
# How much older than the viewer's own request for the stream the newest sample of its first frame
# with data may be: a batch every 0.5 s and the pipe's delay, with a generous margin (a bound on
# what the tab hands over, not on how fast the browser draws: its frames come after).
HANDED_S = 2.0


def test_a_viewer_that_starts_late_is_handed_the_newest_data_first(server: Server, browser) -> None:  # noqa: ANN001
    """The tab script asks for the live stream before the viewer's app exists (frontend/rerun-tab.js)
    and hands that response to the viewer when it asks. What the proxy sent meanwhile waited in the
    response in the order it came: its window (newest first), then each batch. The viewer ingests
    ~10 ms of messages a frame, so a viewer that started late drew first what was newest at the
    connection, seconds old by then (session 10: a second opening at load 9-10 drew a sample 2.1 s
    behind live, its first data read ~1.8 s old). Now what waited is handed over newest first:
    the viewer's first frame with the run's samples holds the latest batch. And while the app is
    held back, the tab's line already says what it is doing (before: the line waited for the page's
    parse, which the viewer's own script holds)."""
    run, info = _live_run_with_the_viewer_prepared(server, browser)
    viewer = browser.new_page(viewport={"width": 1280, "height": 800})
    viewer.add_init_script(FRAME_STATES)
    stream_requests: list[str] = []
    viewer.on("request", lambda r: r.url.endswith(READ_MESSAGES) and stream_requests.append(r.url))
    held: list = []
    viewer.route("**/rerun/re_viewer.js", lambda route: held.append(route))
    viewer.goto(
        server.url + "/rerun/?url=" + urllib.parse.quote(info["live_url"], safe=""),
        wait_until="commit",
        timeout=120_000,
    )
    # (route handlers and request events run inside Playwright calls: the evaluate lets them in)
    wait_for(lambda: viewer.evaluate("0") == 0 and held and stream_requests, 120, "the stream asked for, the app held")
    asked = time.monotonic()
    wait_for(lambda: time.monotonic() - asked >= HOLD_S, HOLD_S + 5, "the viewer held back")  # on purpose
    status = viewer.evaluate(
        "(() => { const b = document.getElementById('xrf-live-status'); "
        "return b && [b.dataset.step, b.textContent, getComputedStyle(b).display]; })()"
    )
    assert status is not None and status[0] == "starting" and "starting the viewer" in status[1], status
    assert status[2] != "none", status
    assert viewer.evaluate("xrfRerunTab.frames().early") == "asked"

    held[0].continue_()
    viewer.wait_for_function("() => window._handle !== undefined", timeout=300_000)
    recording = f"run-{run['id']}"

    def first_drawn() -> int | None:
        for _, state, _ in viewer.evaluate("window._xrfFrameStates"):
            _, newest = viewer_time_range(bytes(state), recording)
            if newest is not None:
                return newest
        return None

    newest = wait_for(first_drawn, FIRST_S, "the viewer's first frame with the run's samples")
    tab = viewer.evaluate("xrfRerunTab.frames()")
    assert tab["early"] == "used" and len(stream_requests) == 1, (tab, stream_requests)
    behind = tab["viewerAskedAt"] / 1e3 - newest / 1e9
    assert behind <= HANDED_S, (
        f"the viewer's first frame with data held samples at most as new as {behind:.1f} s before it asked for "
        f"the stream (it was held back {HOLD_S:g} s after the tab asked): what waited was handed over oldest first"
    )
    viewer.close()
    server.stop_run()


# The page's thread is kept busy this long from the moment the tab script asked for the live
# stream (by a synchronous request the test holds), as the viewer's own start keeps it busy
# (instantiating its wasm, its first frames in software WebGL: 0.5-3 s on a loaded 2-core VM,
# bench/README.md session 12). The stream's window and several batches come meanwhile.
BUSY_S = 6.0

# In the viewer's tab, before its scripts: once the tab script has asked for the live stream, the
# page's thread is busy until the test answers a synchronous request, and in the same task it asks
# for the stream as the viewer does (the viewer's own script is held back: this is the request the
# tab hands its early response to) and keeps what the first reads hand over (2 s of them).
BUSY_THEN_ASK = """if (location.pathname.startsWith("/rerun/")) (() => {
  window._xrfHanded = null;
  const poll = setInterval(() => {
    const tab = window.xrfRerunTab;
    if (!tab || !tab.frames || tab.frames().early !== "asked") return;
    clearInterval(poll);
    const busy = new XMLHttpRequest();
    busy.open("GET", "/xrf-test-busy", false);
    try { busy.send(); } catch (e) { /* the answer does not matter, only when it comes */ }
    const askedAt = Date.now();
    fetch("READ_MESSAGES", { method: "POST", body: new Uint8Array(5), credentials: "same-origin",
      headers: { "content-type": "application/grpc-web+proto", "x-grpc-web": "1" } }).then(async (res) => {
      const reader = res.body.getReader(), got = [];
      const timeUp = new Promise((resolve) => setTimeout(() => resolve({ done: true }), 2000));
      for (;;) {
        const { done, value } = await Promise.race([reader.read(), timeUp]);
        if (done) break;
        got.push(Array.from(value));
      }
      reader.cancel();
      window._xrfHanded = { askedAt, bytes: got.flat() };
    }).catch((e) => { window._xrfHanded = { error: String(e) }; });
  }, 0);
})();""".replace("READ_MESSAGES", READ_MESSAGES)


def test_a_busy_page_still_hands_the_newest_batch_first(server: Server, browser) -> None:  # noqa: ANN001
    """The tab script's early response was read on the page's own thread, which the viewer's start
    keeps busy: what came meanwhile (the proxy's window, then the batches after it, seconds apart)
    was read as one, in the order it came, when the thread was free, and handed over so: the
    viewer's first frame drew the window, the oldest (session 12: 2.16 s behind live). Now it is
    read in a worker, each batch when it comes, and handed over newest first whatever the page's
    thread was doing: the first of the run's samples handed to the viewer is from the newest batch
    held, not the window from when the page's thread went busy (BUSY_S before)."""
    run, info = _live_run_with_the_viewer_prepared(server, browser)
    viewer = browser.new_page(viewport={"width": 1280, "height": 800})
    viewer.add_init_script(BUSY_THEN_ASK)
    held: list = []
    viewer.route("**/rerun/re_viewer.js", lambda route: held.append(route))  # the viewer's app: not started
    busy: list = []
    viewer.route("**/xrf-test-busy", lambda route: busy.append(route))
    viewer.goto(
        server.url + "/rerun/?url=" + urllib.parse.quote(info["live_url"], safe=""),
        wait_until="commit",
        timeout=120_000,
    )
    # (route handlers run inside Playwright calls: one that needs nothing of the busy page)
    wait_for(lambda: viewer.context.cookies() is not None and busy, 120, "the page's thread busy after the tab asked")
    went_busy = time.monotonic()
    wait_for(lambda: time.monotonic() - went_busy >= BUSY_S, BUSY_S + 5, "the page kept busy")  # on purpose
    busy[0].fulfill(status=204)
    handed = wait_for(lambda: viewer.evaluate("window._xrfHanded"), 60, "what the tab handed over")
    assert "error" not in handed, handed
    assert viewer.evaluate("xrfRerunTab.frames().early") == "used"
    asked_ns = handed["askedAt"] * 1_000_000
    frames, _ = split_frames(bytes(handed["bytes"]))
    recording = f"run-{run['id']}"
    times = []
    for flag, payload in frames:
        chunk = chunk_of(payload) if flag == 0 else None
        if chunk is not None and chunk.store_kind == STORE_RECORDING and chunk.newest_time_ns is not None:
            assert chunk.recording_id == recording, chunk.recording_id
            times.append(chunk.newest_time_ns)
    assert times, "the tab handed over none of the run's samples"
    # What waited was the window from before the page went busy and the batches after it...
    assert (asked_ns - min(times)) / 1e9 >= BUSY_S / 2, [(asked_ns - t) / 1e9 for t in times]
    # ...and the first handed over is the newest batch, not that window.
    assert (asked_ns - times[0]) / 1e9 <= HANDED_S, (
        f"the first of the run's samples handed to the viewer was {(asked_ns - times[0]) / 1e9:.1f} s older than "
        f"its request (the page was busy {BUSY_S:g} s before it): handed over in the order it came, oldest first"
    )
    held.clear()
    viewer.close()
    server.stop_run()


# In the viewer's tab, before its scripts: each frame callback's WebGL shader compiles and program
# links (the viewer makes its render pipelines when it first draws plots), and at its end the
# viewer's state, whether its canvas was visible and whether the tab's line was on screen: kept
# when any of these changed or the frame compiled.
GL_FRAMES = """if (location.pathname.startsWith("/rerun/")) (() => {
  const gl = { compiles: 0, links: 0 };
  for (const C of [window.WebGL2RenderingContext, window.WebGLRenderingContext]) {
    if (!C) continue;
    const compile = C.prototype.compileShader, link = C.prototype.linkProgram;
    C.prototype.compileShader = function (...a) { gl.compiles += 1; return compile.apply(this, a); };
    C.prototype.linkProgram = function (...a) { gl.links += 1; return link.apply(this, a); };
  }
  window._xrfGlFrames = [];
  let handle, last = "";
  Object.defineProperty(window, "_handle", { configurable: true, get: () => handle, set: (v) => { handle = v; } });
  const raf = window.requestAnimationFrame.bind(window);
  window.requestAnimationFrame = (cb) => raf((t) => {
    const c0 = gl.compiles, l0 = gl.links;
    cb(t);
    if (!handle || window._xrfGlFrames.length > 2000) return;
    let st;
    try { st = Array.from(handle.viewer_state()); } catch (e) { return; }
    const canvas = document.getElementById("the_canvas_id"), line = document.getElementById("xrf-live-status");
    const style = canvas ? getComputedStyle(canvas) : null;
    const visible = !!style && style.visibility === "visible" && style.opacity !== "0";
    const shown = !!line && getComputedStyle(line).display !== "none";
    const c = gl.compiles - c0, l = gl.links - l0, key = st.join(",") + visible + shown;
    if (c || l || key !== last) { last = key; window._xrfGlFrames.push([c, l, st, visible, shown]); }
  });
})();"""

# The tab's warm-up recording (logs/rerun_warmup.py), as the viewer names it.
WARMUP_STORE = "Recording:xrflab-warmup:warmup"


def test_the_viewer_draws_plots_before_the_runs_first_sample_and_never_shows_them(
    server: Server,
    browser,  # noqa: ANN001
) -> None:
    """Without a GPU driver the viewer's first frame with plots took 0.5-1.2 s by itself: it builds
    its render pipelines then (WebGL programs compiled in software), and that was the frame with
    the run's first samples, so they reached the screen that much older (bench/README.md, session
    13). Now the tab has the viewer draw a small recording of its own first (a time-series plot,
    GET /api/logs/rerun/warmup.rrd), closes it, and only then hands over the run's stream
    (frontend/rerun-tab.js, warm-up): the programs are linked in frames before the run's first
    sample, the frame that draws that sample links none, and a person never sees the made-up
    plots: the canvas is hidden whenever the viewer holds them (the tab's line says what it does),
    they are a recording of another application, gone from the viewer before the run's data, and
    nothing of them is in the run's recording. (How much sooner the sample is on screen is a figure
    of bench/appliance/rerun_lag.py: no timing here.)"""
    run_started_ns = time.time_ns()
    run, info = _live_run_with_the_viewer_prepared(server, browser)
    viewer = browser.new_page(viewport={"width": 1280, "height": 800})
    viewer.add_init_script(GL_FRAMES)
    viewer.goto(server.url + "/rerun/?url=" + urllib.parse.quote(info["live_url"], safe=""), timeout=120_000)
    viewer.wait_for_function("() => window._handle !== undefined", timeout=300_000)
    recording = f"run-{run['id']}"

    def first_drawn() -> tuple[int, list] | None:
        frames = viewer.evaluate("window._xrfGlFrames")
        for i, (_, _, state, _, _) in enumerate(frames):
            if viewer_time_range(bytes(state), recording)[1] is not None:
                return i, frames
        return None

    first, frames = wait_for(first_drawn, FIRST_S, "the viewer's first frame with the run's samples")
    before = frames[:first]
    warm = [f for f in before if viewer_recordings(bytes(f[2])).get(WARMUP_STORE)]
    # The viewer drew plots before the run's first sample: its warm-up recording held samples in
    # frames before it, and the viewer linked its programs in those frames...
    assert warm, "no frame before the run's first sample held the warm-up's plots"
    assert sum(f[1] for f in before) > 0, [(c, k) for c, k, *_ in before if c or k]
    # ...so the frame that drew the run's first sample built no render pipeline of its own.
    compiles, links, state, visible, _ = frames[first]
    assert (compiles, links) == (0, 0), (
        f"the frame with the run's first sample compiled {compiles} shaders and linked {links} programs"
    )
    # The made-up samples never on screen: whenever the viewer held them, its canvas was hidden and
    # the tab's line said what it was doing.
    for *_, st, vis, shown in frames:
        if WARMUP_STORE in viewer_recordings(bytes(st)):
            assert not vis and shown, (vis, shown)
    # From the run's first sample on, the run's recording is the only one, and the active one...
    assert set(viewer_recordings(bytes(state))) == {f"Recording:xrflab:{recording}"}, viewer_recordings(bytes(state))
    assert viewer_active(bytes(state)) == f"Recording:xrflab:{recording}", viewer_active(bytes(state))
    assert visible
    # ...and holds nothing of the warm-up (its samples are from years before this run).
    oldest, _ = viewer_time_range(bytes(state), recording)
    assert oldest is not None and oldest >= run_started_ns, (oldest, run_started_ns)
    tab = viewer.evaluate("xrfRerunTab.frames()")
    assert tab["warmup"]["state"] == "done" and tab["early"] == "used", tab["warmup"]
    later = viewer.evaluate("Array.from(window._handle.viewer_state())")
    assert WARMUP_STORE not in viewer_recordings(bytes(later))
    viewer.close()
    server.stop_run()
