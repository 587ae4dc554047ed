"""The bench lease with real browsers (Debian's chromium via Playwright): two students log in
through the login page in two separate browser contexts, take / queue / release the bench, see
each other's changes live, the inactivity timeout and an educator's take-over."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from xrf_testing.harness import (
    CHROMIUM_ARGS,
    Server,
    browser_login,
    session_cookies,
    shared_builds_root,
    start_server,
    stop_server,
)

IDLE_S = 8.0
ERRORS: list[str] = []  # uncaught JavaScript errors of every page


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    s = start_server(tmp_path_factory.mktemp("data"), shared_builds_root(), lease_idle_s=IDLE_S)
    yield s
    stop_server(s)


@pytest.fixture(scope="module")
def browser(chromium_path: str) -> Iterator[object]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=chromium_path, args=CHROMIUM_ARGS)
        yield b
        b.close()


def page_for(browser, server: Server, username: str, password: str):  # type: ignore[no-untyped-def]
    ctx = browser.new_context(viewport={"width": 1300, "height": 900})  # its own cookies: a second person
    page = ctx.new_page()
    page.on("pageerror", lambda e: ERRORS.append(f"{username}: {e}"))
    browser_login(page, server.url, username, password)
    page.wait_for_function("document.getElementById('conn').textContent === 'connected'")
    return page


def holder_is(page, text: str, timeout: float = 10_000) -> None:  # type: ignore[no-untyped-def]
    page.wait_for_function(f"document.getElementById('lease-holder').textContent === {text!r}", timeout=timeout)


def notice_says(page, fragment: str, timeout: float = 10_000) -> None:  # type: ignore[no-untyped-def]
    page.wait_for_function(
        f"!document.getElementById('notice').classList.contains('hidden')"
        f" && document.getElementById('notice-text').textContent.includes({fragment!r})",
        timeout=timeout,
    )


def test_two_students_hand_over_queue_timeout_and_take_over(server: Server, browser) -> None:
    alice_pw = server.create_user("alice", "student")
    bob_pw = server.create_user("bob", "student")
    alice = page_for(browser, server, "alice", alice_pw)
    bob = page_for(browser, server, "bob", bob_pw)
    holder_is(alice, "free")
    holder_is(bob, "free")
    assert alice.inner_text("#me-name") == "alice · student"
    assert not alice.is_visible("#nav a[data-page=users]")  # the Users page is for educators

    # Alice takes the bench; Bob sees it at once and can only queue.
    alice.click("#btn-lease-take")
    holder_is(alice, "you")
    holder_is(bob, "alice")
    assert bob.is_visible("#btn-lease-queue") and not bob.is_visible("#btn-lease-take")
    bob.click("#btn-lease-queue")
    alice.wait_for_function("document.getElementById('lease-queue').textContent === 'queue: bob'")

    # Alice drives: starts a relbot run from the dashboard.
    alice.wait_for_selector("#build-select option[value=relbot]", state="attached")
    alice.select_option("#build-select", "relbot")
    alice.click("#btn-start-run")
    bob.wait_for_function("document.getElementById('state-name').textContent === 'IDLE'", timeout=120_000)
    # Bob's STOP outside RUN/PAUSED would end Alice's run: it explains instead.
    bob.click("#btn-estop")
    notice_says(bob, "You do not hold the bench")
    assert server.http.get("/api/status").json()["run_active"]
    alice.click("#commands [data-cmd=initialise]")
    bob.wait_for_function("document.getElementById('state-name').textContent === 'INITIALISED'")

    # Alice releases: the bench goes to Bob, who is told.
    alice.click("#btn-lease-release")
    holder_is(bob, "you")
    holder_is(alice, "bob")
    notice_says(bob, "The bench is yours now")
    bob.click("#commands [data-cmd=start]")
    alice.wait_for_function("document.getElementById('state-name').textContent === 'RUN'")
    # Stopping is always allowed: Alice (not holding) presses STOP in RUN.
    alice.click("#btn-estop")
    bob.wait_for_function("document.getElementById('state-name').textContent === 'STOPPED'")

    # Bob does nothing: the bench is released after the inactivity time, and Bob is told.
    holder_is(bob, "free", timeout=(IDLE_S + 5) * 1000)
    notice_says(bob, "nothing was driven")
    holder_is(alice, "free")

    # Alice takes it again; an educator takes it over; Alice is told.
    alice.click("#btn-lease-take")
    holder_is(bob, "alice")
    ctx = browser.new_context(viewport={"width": 1300, "height": 900})
    ctx.add_cookies(session_cookies(server.http, server.url))
    edu = ctx.new_page()
    edu.goto(server.url + "/")
    holder_is(edu, "alice")
    edu.click("#btn-lease-takeover")
    holder_is(edu, "you")
    holder_is(alice, "admin")
    notice_says(alice, "took over the bench")
    assert edu.is_visible("#nav a[data-page=users]")
    server.stop_run()
    assert not ERRORS, ERRORS
    for p in (alice, bob, edu):
        p.context.close()


def test_first_login_forces_a_password_change(server: Server, browser) -> None:
    r = server.http.post("/api/users", json={"username": "carol", "role": "observer"})
    secret = r.json()["password"]
    ctx = browser.new_context()
    page = ctx.new_page()
    page.goto(server.url + "/#bench")
    page.wait_for_selector("#login-user")
    page.fill("#login-user", "carol")
    page.fill("#login-pass", "not it at all")
    page.click("#login-submit")
    page.wait_for_function("document.getElementById('login-error').textContent.includes('wrong')")
    page.fill("#login-pass", secret)
    page.click("#login-submit")
    page.wait_for_selector("#change-form:not(.hidden)")
    page.fill("#change-new", "carols own password")
    page.fill("#change-again", "carols own password")
    page.click("#change-submit")
    page.wait_for_function(
        "document.getElementById('me-name') && document.getElementById('me-name').textContent === 'carol · observer'"
    )
    # Observers watch: no lease buttons; STOP is off and says why, and Esc explains.
    assert not page.is_visible("#btn-lease-take")
    page.wait_for_function("document.getElementById('btn-estop').disabled")
    assert "watch only" in page.get_attribute("#btn-estop", "title")
    page.keyboard.press("Escape")
    notice_says(page, "Observers watch only")
    page.click("#btn-logout")
    page.wait_for_selector("#login-user")
    ctx.close()


def test_users_page_creates_and_imports(server: Server, browser) -> None:
    ctx = browser.new_context(viewport={"width": 1300, "height": 900})
    ctx.add_cookies(session_cookies(server.http, server.url))
    page = ctx.new_page()
    page.goto(server.url + "/#users")
    page.wait_for_selector("#u-create")
    page.fill("#u-name", "dave")
    page.fill("#u-full", "Dave D")
    page.click("#u-create-btn")
    page.wait_for_selector("#u-secret")
    page.wait_for_selector("#user-dave")
    page.fill("#u-csv", "erin,Erin E,student\nfrank,Frank F,observer\n")
    page.click("#u-import")
    page.wait_for_function("document.getElementById('u-import-result').textContent.includes('2 accounts created')")
    page.wait_for_selector("#user-frank")
    page.click("#a-filter button[type=submit]")
    page.wait_for_function("document.getElementById('a-body').textContent.includes('user.import')")
    ctx.close()
