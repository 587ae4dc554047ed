"""Small things a first afternoon tripped over (issue 31, bug 8), in a real browser (Debian's
chromium) against a real appliance: a page path typed without its ``#`` (``/users``) opens that
dashboard page instead of the API's JSON 404, the tab's icon is served (locally), and the
editor's diff says "1 file changed"."""

from __future__ import annotations

import struct

from xrf_testing.harness import Server


def test_page_path_without_hash_opens_the_dashboard_page(server: Server, browser) -> None:  # noqa: ANN001
    page = browser.new_page()
    not_found: list[str] = []
    page.on("response", lambda r: not_found.append(r.url) if r.status == 404 else None)
    page.goto(server.url + "/users")
    page.wait_for_function("location.hash === '#users'")
    assert page.url == server.url + "/#users"
    # The Users page itself, not raw JSON.
    page.wait_for_selector("#u-create", state="visible")
    assert "Not Found" not in page.content()
    # A deeper unknown path: a page saying so with a link home, still not JSON.
    r = page.goto(server.url + "/users/7/nothing")
    assert r is not None and r.status == 404 and r.headers["content-type"].startswith("text/html")
    assert page.locator("a[href='/']").count() == 1
    # The API answers programs as before: JSON, under its own path.
    api = page.request.get(server.url + "/api/no-such-thing")
    assert api.status == 404 and api.headers["content-type"] == "application/json"
    assert api.json() == {"detail": "Not Found"}
    assert not [u for u in not_found if not u.endswith("/users/7/nothing")], not_found
    page.context.close()


def test_favicon_is_served_locally(server: Server, browser) -> None:  # noqa: ANN001
    page = browser.new_page()
    r = page.goto(server.url + "/favicon.ico")
    assert r is not None and r.status == 200 and r.headers["content-type"] == "image/x-icon"
    body = r.body()
    reserved, kind, count = struct.unpack_from("<HHH", body)
    assert (reserved, kind, count) == (0, 1, 1)  # an ICO with one image
    width, height = body[6], body[7]
    assert (width, height) == (32, 32)
    # Logged out too (the login page asks for it).
    fresh = browser.browser.new_context().new_page()
    assert fresh.request.get(server.url + "/favicon.ico").status == 200
    fresh.context.close()
    page.context.close()


def test_diff_of_one_file_says_1_file_changed(server: Server, browser) -> None:  # noqa: ANN001
    r = server.http.post("/api/projects/from-template", json={"template": "base", "name": "ui_plural"})
    assert r.status_code == 201, r.text
    pid = r.json()["id"]
    src = server.http.get(f"/api/projects/{pid}/files/src/Template.cpp").json()["content"]
    saved = server.http.put(
        f"/api/projects/{pid}/files/src/Template.cpp?build=false", content=(src + "\n// one change\n").encode()
    )
    assert saved.status_code == 200 and saved.json()["new_version"], saved.text
    n = saved.json()["version"]["n"]
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.goto(server.url + "/#editor")
    page.wait_for_function("window.xrfEditor && window.xrfEditor.cm")
    page.wait_for_selector(f"#ed-project option[value='{pid}']", state="attached")
    page.select_option("#ed-project", str(pid))
    page.wait_for_function(f"xrfEditor.pid === {pid}")
    page.click(f"#ed-versions li[data-n='{n}']")
    page.wait_for_selector(".ed-diff-file[data-path='src/Template.cpp']")
    summary = page.text_content(".ed-diff-sum")
    assert summary.endswith(": 1 file changed, +2 −0"), summary  # the blank line and the comment
    page.context.close()


def _notice_says(page, fragment: str, timeout: float = 15_000) -> None:  # noqa: ANN001
    page.wait_for_function(
        "(f) => !document.getElementById('notice').classList.contains('hidden')"
        " && document.getElementById('notice-text').textContent.includes(f)",
        arg=fragment,
        timeout=timeout,
    )


def test_holder_is_told_who_paused_and_a_taken_over_student_queues_first(server: Server, raw_browser) -> None:  # noqa: ANN001
    """Bob (not holding) pauses Alice's run: Alice's dashboard names him. An educator takes the
    bench over from Alice: she is first in the queue, told so, and gets it back at the release."""
    from xrf_testing.harness import browser_login, login_client

    server.stop_run()
    alice_pw = server.create_user("alice8", "student")
    bob_pw = server.create_user("bob8", "student")
    carl_pw = server.create_user("carl8", "student")
    alice_http = login_client(server.url, "alice8", alice_pw)
    bob_http = login_client(server.url, "bob8", bob_pw)
    carl_http = login_client(server.url, "carl8", carl_pw)
    ctx = raw_browser.new_context(viewport={"width": 1300, "height": 900})
    try:
        page = ctx.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        browser_login(page, server.url, "alice8", alice_pw)
        page.wait_for_function("document.getElementById('conn').textContent === 'connected'")
        assert alice_http.post("/api/lease/take").status_code == 200
        page.wait_for_function("document.getElementById('lease-holder').textContent === 'you'")
        assert alice_http.post("/api/runs", json={"build": "relbot"}, timeout=300).status_code == 201
        for cmd in ("initialise", "start"):
            r = alice_http.post("/api/runs/current/command", json={"cmd": cmd})
            assert r.status_code == 200 and r.json()["accepted"], r.text
        page.wait_for_function("document.getElementById('state-name').textContent === 'RUN'", timeout=30_000)

        r = bob_http.post("/api/runs/current/command", json={"cmd": "pause"})  # the STOP rule: allowed
        assert r.status_code == 200 and r.json()["accepted"], r.text
        _notice_says(page, "bob8 paused your run")

        # Carl queues; the educator takes over: Alice goes to the queue's head, before Carl.
        assert carl_http.post("/api/lease/queue").status_code == 200
        assert server.http.post("/api/lease/take").status_code == 200
        _notice_says(page, "first in the queue")
        page.wait_for_function("document.getElementById('lease-queue').textContent === 'queue: alice8, carl8'")
        assert server.http.post("/api/lease/release").status_code == 200
        page.wait_for_function("document.getElementById('lease-holder').textContent === 'you'")
        _notice_says(page, "The bench is yours now")
        assert not errors, errors
    finally:
        server.stop_run()
        server.http.post("/api/lease/release")
        ctx.close()
        for h in (alice_http, bob_http, carl_http):
            h.close()
