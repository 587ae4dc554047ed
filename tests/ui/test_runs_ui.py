"""The Runs page in a real browser: the run list with its logging figures and lost badge, a CSV
download through the browser (Playwright's download API) equal to `xrf decode`'s CSV, and the
rerun viewer from the appliance, opened in a tab of its own."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import parse_qs, quote, urlsplit

import httpx
import pytest

from xrf_testing.harness import (
    ADMIN_PASSWORD,
    ADMIN_USER,
    Server,
    browser_login,
    login_client,
    shared_builds_root,
    start_server,
    stop_server,
    wait_for,
)
from xrf_testing.net import lan_address

REPO = Path(__file__).resolve().parents[2]
PROBE = "logs-probe"


def live_viewer_url(opened: str) -> tuple[str, str]:
    """(origin, the stream URL it was given) of a live viewer tab's URL: /rerun/?url=...; the live
    tab's script may add hide_welcome_screen to the query (frontend/rerun-tab.js)."""
    parts = urlsplit(opened)
    assert parts.path == "/rerun/", opened
    return f"{parts.scheme}://{parts.netloc}", parse_qs(parts.query)["url"][0]


def _projects() -> Path:
    root = REPO / ".cache" / "logs-appliance-projects" / "examples"
    root.mkdir(parents=True, exist_ok=True)
    link = root / PROBE
    if not link.is_symlink():
        link.symlink_to(REPO / "tests/fixtures/loop_probe")
    return root.parent


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    # every interface, so the live test can open the appliance by its LAN address
    s = start_server(
        tmp_path_factory.mktemp("data"), shared_builds_root(), projects_dir=str(_projects()), host="0.0.0.0"
    )
    yield s
    stop_server(s)


def test_runs_page_lists_runs_and_downloads_a_csv(server: Server, browser, tmp_path: Path) -> None:
    run = server.start_run(PROBE)
    for cmd in ("initialise", "start"):
        assert server.http.post("/api/runs/current/command", json={"cmd": cmd}).json()["accepted"]
    server.wait_cycles(run["id"], 100)
    server.stop_run()
    info = server.http.get(f"/api/logs/runs/{run['id']}").json()
    name = info["files"][0]["name"]

    page = browser.new_page(accept_downloads=True)
    requested: list[str] = []
    page.on("request", lambda r: requested.append(r.url))
    page.goto(server.url + "/#runs")
    row = page.locator(f"#runs-row-{run['id']}")
    row.wait_for(timeout=15000)
    text = row.inner_text()
    assert PROBE in text and "ended" in text and "lost: 0" in text
    assert row.locator(".lost-badge.bad").count() == 0
    row.click()
    link = page.locator('#rl-files a.dl[data-fmt="csv"]')
    link.wait_for(timeout=10000)
    with page.expect_download() as dl:
        link.click()
    download = dl.value
    assert download.suggested_filename == f"run{run['id']}_{Path(name).stem}.csv"
    got = tmp_path / "browser.csv"
    download.save_as(got)
    env = dict(os.environ, PYTHONPATH=str(REPO / "appliance"))
    want = tmp_path / "cli.csv"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "xrflab.cli",
            "decode",
            str(server.data_dir / "runs" / str(run["id"]) / name),
            "--to",
            "csv",
            "-o",
            str(want),
        ],
        check=True,
        env=env,
        capture_output=True,
    )
    assert got.read_bytes() == want.read_bytes()
    assert got.read_text().count("\n") == info["files"][0]["records"] + 1
    # The rerun viewer is loaded only when asked for (not to download a CSV)...
    assert page.context.pages == [page]
    assert not [u for u in requested if "/rerun/" in u], requested
    assert page.locator("iframe").count() == 0
    # ...in a tab of its own (no opener: its own renderer process), from the appliance (not a
    # CDN), its live stream on this origin.
    with page.context.expect_page() as opened:
        page.click("#rr-live")
    viewer = opened.value
    viewer.wait_for_url("**/rerun/**", wait_until="commit", timeout=300_000)
    port = server.url.rsplit(":", 1)[1]
    assert live_viewer_url(viewer.url) == (server.url, f"rerun+http://127.0.0.1:{port}/proxy"), viewer.url
    assert viewer.evaluate("window.opener") is None
    viewer.close()
    console: list[str] = []  # the viewer's own messages, said when it does not show the log
    page.context.on("page", lambda p: p.on("console", lambda m: console.append(m.text[:300])))
    with page.context.expect_page() as opened:
        page.locator(".open-rrd").first.click()
    viewer = opened.value
    viewer.wait_for_url("**/rerun/**", wait_until="commit", timeout=300_000)
    opened_url = parse_qs(urlsplit(viewer.url).query)["url"][0]
    # A link of the viewer's own, ending in .rrd: rerun 0.41's viewer refuses an http URL without
    # a file extension it knows ("Failed to parse URL") and sends no cookie (401): either was an
    # empty viewer, the ?fmt=rrd link of before.
    assert opened_url.startswith(f"{server.url}/api/logs/viewer/") and opened_url.endswith(f"/{quote(name)}.rrd")
    assert server.url + page.get_attribute("#rr-link", "href") == viewer.url  # the link to open it again
    # The web viewer reads the download (the child's .rrd, logs/rrdfile.py, not the SDK's): it holds
    # the log's samples, on the `time` line from its first record to its last.
    rrd = httpx.get(opened_url, timeout=120)  # no cookie, as the viewer fetches it
    assert rrd.status_code == 200 and rrd.content[:4] == b"RRF2" and rrd.content[8] == 0, rrd.content[:12]
    _viewer_holds_the_log(viewer, server.data_dir / "runs" / str(run["id"]) / name, console)
    page.context.close()


def _viewer_holds_the_log(viewer, log_path: Path, console: list[str]) -> None:  # noqa: ANN001
    from playwright.sync_api import Error as PlaywrightError

    from xrf_testing.rerun_stream import viewer_time_range
    from xrflab.logs.reader import open_log

    log = open_log(log_path)
    want = (
        int(log.segments[0].wall_ns(log.segments[0].records["t_ns"][:1])[0]),
        int(log.segments[-1].wall_ns(log.segments[-1].records["t_ns"][-1:])[0]),
    )
    held: tuple[int | None, int | None] = (None, None)
    deadline = time.monotonic() + 120
    while held != want:
        assert time.monotonic() < deadline, (held, want, console[-15:])
        try:
            state = bytes(viewer.evaluate("Array.from(window._handle.viewer_state())"))
        except PlaywrightError:  # the viewer's app is not there yet
            state = b""
        held = viewer_time_range(state, log_path.name)
        time.sleep(0.5)


VIEWER_READS = """if (location.pathname.startsWith("/rerun/")) (() => {
  window._xrfReads = [];
  const read = ReadableStreamDefaultReader.prototype.read;
  ReadableStreamDefaultReader.prototype.read = function (...a) {
    return read.apply(this, a).then((r) => {
      if (!r.done && r.value && window._xrfReads.length < 5000) window._xrfReads.push(Array.from(r.value));
      return r;
    });
  };
})();"""


def test_live_plots_from_the_lan_address(server: Server, raw_browser) -> None:
    """A browser that opened the appliance by its LAN address logs in, and the rerun viewer (in
    its own tab) receives the running run's live recording through the appliance's origin (its
    tab's stream request, answered, and what the viewer reads of it: the tab script fetches it in
    a worker and hands it over, frontend/rerun-tab.js)."""
    port = server.url.rsplit(":", 1)[1]
    url = f"http://{lan_address()}:{port}"
    http = login_client(url, ADMIN_USER, ADMIN_PASSWORD)
    ctx = raw_browser.new_context(viewport={"width": 1400, "height": 1000})
    try:
        server.stop_run()
        run = http.post("/api/runs", json={"build": PROBE}, timeout=300).json()
        for cmd in ("initialise", "start"):
            assert http.post("/api/runs/current/command", json={"cmd": cmd}).json()["accepted"]
        deadline = time.monotonic() + 20
        while http.get("/api/logs/rerun").json()["live_run"] != run["id"]:
            assert time.monotonic() < deadline, "the run's live stream did not start"
            time.sleep(0.1)

        page = ctx.new_page()
        browser_login(page, url, ADMIN_USER, ADMIN_PASSWORD)
        stream: dict[str, object] = {"status": None, "data": b""}

        def on_response(r) -> None:  # noqa: ANN001  (the tab's worker's requests are reported on its page)
            if r.url == url + "/rerun.sdk_comms.v1alpha1.MessageProxyService/ReadMessages":
                stream["status"] = r.status

        # In the viewer's tab, before its scripts: what the viewer reads of a stream (the live one
        # is the only stream it reads on its page's thread).
        ctx.add_init_script(VIEWER_READS)
        page.goto(url + "/#runs")
        ctx.on("page", lambda viewer: viewer.on("response", on_response))
        with ctx.expect_page() as opened:
            page.click("#rr-live")
        viewer = opened.value
        viewer.wait_for_url("**/rerun/**", wait_until="commit", timeout=300_000)
        assert live_viewer_url(viewer.url) == (url, f"rerun+{url}/proxy"), viewer.url
        assert f"live: run {run['id']}" in page.locator("#rr-what").inner_text()
        # the viewer (a 40 MB wasm) starts and reads the live stream: seconds on a slow machine
        want = f"run-{run['id']}".encode()
        deadline = time.monotonic() + 120
        while not (want in stream["data"] and b"ratio" in stream["data"]):  # type: ignore[operator]
            assert time.monotonic() < deadline, ("the viewer received no data of the live run", stream["status"])
            viewer.wait_for_timeout(250)
            got = viewer.evaluate("window._xrfReads ? window._xrfReads.splice(0) : []")
            stream["data"] += b"".join(bytes(chunk) for chunk in got)  # type: ignore[operator]
        assert stream["status"] == 200
        shots = os.environ.get("XRF_SCREENSHOTS")  # the picture in docs/logging/appliance.md
        if shots:
            viewer.wait_for_timeout(5000)
            viewer.screenshot(path=str(Path(shots) / "runs-live-rerun.png"))
    finally:
        ctx.close()
        http.close()
        server.stop_run()


# The viewer's code, as its page fetches it (frontend/rerun-tab.js, rerun's index.html).
VIEWER_WASM = "/rerun/re_viewer_bg.wasm"


def test_the_runs_page_has_the_live_viewers_code_cached_before_live_plots(
    server: Server, raw_browser, chromium_path: str, tmp_path: Path
) -> None:
    """While a live run is listed, the Runs page gets the viewer's code (14 MB of compressed wasm, its
    script) into the browser's cache (frontend/pages/runs.js), so the first "Live plots" does not
    start by downloading it (issue 31 bug 6, session 11); with no live run it fetches nothing. A
    browser profile on disk, as a person's: Playwright's off-the-record contexts keep no entry that
    large."""
    from xrf_testing.harness import CHROMIUM_ARGS, session_cookies

    server.stop_run()
    assert server.http.get("/rerun/index.html", timeout=600).status_code == 200  # the viewer's files prepared
    ctx = raw_browser.browser_type.launch_persistent_context(
        str(tmp_path / "profile"),
        executable_path=chromium_path,
        args=CHROMIUM_ARGS,
        viewport={"width": 1280, "height": 800},
    )
    try:
        ctx.add_cookies(session_cookies(server.http, server.url))
        fetched: list[str] = []
        dash = ctx.new_page()
        dash.on("requestfinished", lambda r: r.url.endswith(VIEWER_WASM) and fetched.append(r.url))
        with dash.expect_response(lambda r: "/api/logs/runs?" in r.url, timeout=60_000):
            dash.goto(server.url + "/#runs")
        dash.wait_for_function("() => Array.isArray(xrf.runsList)", timeout=60_000)
        assert dash.evaluate("xrf.runsList.some((r) => r.live)") is False
        assert not fetched, "the Runs page fetched the viewer's code with no live run"

        run = server.start_run(PROBE)
        with server.ws() as ws:
            ws.to_run()
        wait_for(lambda: server.http.get("/api/logs/rerun").json()["live_running"], 30, "the live stream")
        # (the page's 2 s poll lists the run; request events reach the list inside Playwright calls)
        wait_for(lambda: dash.evaluate("0") == 0 and fetched, 120, "the Runs page to fetch the viewer's code")
        with ctx.expect_page(timeout=120_000) as popup:
            dash.click("#rr-live")
        viewer = popup.value
        viewer.wait_for_function("() => window._handle !== undefined", timeout=300_000)
        transfer = viewer.evaluate(
            f"performance.getEntriesByType('resource').find((e) => e.name.endsWith('{VIEWER_WASM}')).transferSize"
        )
        assert transfer == 0, f"the viewer's first opening fetched {transfer} bytes of its wasm: not from the cache"
        assert run["id"] == server.http.get("/api/logs/rerun").json()["live_run"]
    finally:
        ctx.close()
        server.stop_run()


def test_timing_per_cycle_from_the_bench_page(server: Server, browser) -> None:
    """Ticking "timing per cycle" before "Start run" gives the run a cycle_timing.xrf log."""
    server.stop_run()
    page = browser.new_page()
    try:
        page.goto(server.url + "/")
        page.wait_for_function(
            f"[...document.querySelectorAll('#build-select option')].some(o => o.value === '{PROBE}')"
        )
        page.select_option("#build-select", PROBE)
        page.check("#log-timing")
        page.click("#btn-start-run")
        deadline = time.monotonic() + 60
        while not (runs := server.http.get("/api/logs/runs?limit=1").json()) or runs[0]["status"] != "running":
            assert time.monotonic() < deadline, "the run did not start"
            time.sleep(0.1)
        run_id = runs[0]["id"]
        for cmd in ("initialise", "start"):
            assert server.http.post("/api/runs/current/command", json={"cmd": cmd}).json()["accepted"]
        server.wait_cycles(run_id, 100)
        server.stop_run()
        files = {f["name"]: f for f in server.http.get(f"/api/logs/runs/{run_id}").json()["files"]}
        assert "cycle_timing.xrf" in files and files["cycle_timing.xrf"]["records"] > 100
    finally:
        page.close()
