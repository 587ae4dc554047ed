"""The rerun viewer works offline (issue 19): opened from the Runs page with a live run (in a tab
of its own), it starts, reads the live stream, and nothing a student's browser loads goes anywhere
but the appliance (every request of every page, frame and worker of the browser context is
recorded: the viewer's tab is a page of that context). Its files come compressed."""

from __future__ import annotations

import time
from urllib.parse import urlsplit

from xrf_testing.harness import Server


def test_viewer_fetches_nothing_from_the_internet(server: Server, browser) -> None:  # noqa: ANN001
    server.stop_run()
    run = server.start_run("relbot")
    for cmd in ("initialise", "start"):
        assert server.http.post("/api/runs/current/command", json={"cmd": cmd}).json()["accepted"]
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    ctx = page.context
    requests: list[str] = []
    ctx.on("request", lambda r: requests.append(r.url))  # pages (the viewer's tab too), frames, workers
    ctx.on("serviceworker", lambda w: requests.append("serviceworker:" + w.url))
    ctx.on("weberror", lambda e: requests.append("error:" + str(e.error)))
    try:
        page.goto(server.url + "/#runs")
        with ctx.expect_page() as opened:
            page.click("#rr-live")
        viewer = opened.value
        # rerun's index.html sets window._handle once the app runs (a 43 MB wasm on a software
        # renderer); a function, not a string: the viewer's CSP forbids eval
        viewer.wait_for_function("() => window._handle !== undefined", timeout=180_000, polling=500)
        stream = "/rerun.sdk_comms.v1alpha1.MessageProxyService/ReadMessages"
        deadline = time.monotonic() + 30
        while not any(u.endswith(stream) for u in requests):
            assert time.monotonic() < deadline, "the viewer never opened the live stream"
            page.wait_for_timeout(250)
        # what rerun fetched by itself came within seconds of starting (analytics, version check,
        # examples): give it time
        page.wait_for_timeout(10_000)
        assert viewer.evaluate("document.querySelector('#the_canvas_id') !== null")
        assert viewer.evaluate("typeof window.xrfRerunTab") == "object"  # ours, allowed by the CSP
    finally:
        ctx.close()
        server.stop_run()
    appliance = urlsplit(server.url).netloc
    elsewhere = [u for u in requests if urlsplit(u).scheme not in ("data", "blob") and urlsplit(u).netloc != appliance]
    assert not elsewhere, elsewhere
    assert any("/rerun/re_viewer_bg.wasm" in u for u in requests)
    assert run["id"]


def test_viewer_files_are_served_gzipped_and_confined(server: Server) -> None:
    r = server.http.get("/rerun/re_viewer_bg.wasm", headers={"Accept-Encoding": "gzip"}, timeout=300)
    assert r.status_code == 200
    assert r.headers["content-encoding"] == "gzip"
    assert r.headers["content-type"] == "application/wasm"
    assert "max-age" in r.headers["cache-control"]
    assert "connect-src 'self'" in r.headers["content-security-policy"]
    compressed = int(r.headers["content-length"])
    assert len(r.content) == int(r.headers["rerun-final-length"]) > 2 * compressed  # httpx decoded it
    assert r.content[:4] == b"\0asm"
    for url in (b"https://tel.rerun.io", b"https://api.github.com", b"https://app.rerun.io"):
        assert url not in r.content, url
    index = server.http.get("/rerun/", headers={"Accept-Encoding": "gzip"})
    assert index.headers["cache-control"] == "no-cache" and "googleapis" not in index.text
    # our script (Esc stops the run from the viewer's tab), from this origin, as the CSP allows
    assert '<script src="/static/rerun-tab.js"></script>' in index.text
    assert "script-src 'self'" in index.headers["content-security-policy"]
    assert "Escape" in server.http.get("/static/rerun-tab.js").text
    plain = server.http.get("/rerun/re_viewer.js", headers={"Accept-Encoding": "identity"})
    assert "content-encoding" not in plain.headers
    assert len(plain.content) == int(plain.headers["content-length"]) == int(plain.headers["rerun-final-length"])
    assert server.http.get("/rerun/offline/tel.rerun.io_").status_code == 404
