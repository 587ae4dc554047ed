"""Browser tests: Debian's chromium driven by Playwright against a real appliance."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from xrf_testing.harness import (  # noqa: F401
    CHROMIUM_ARGS,
    Server,
    browser_login,
    session_cookies,
    shared_builds_root,
    start_server,
    stop_server,
)


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    s = start_server(tmp_path_factory.mktemp("data"), shared_builds_root())
    yield s
    stop_server(s)


class LoggedInBrowser:
    """The browser, but every new_page() is a fresh context already logged in as the harness's
    educator (the session of server.http). Anything else is the Playwright Browser's."""

    def __init__(self, browser: object, server: Server) -> None:
        self.browser = browser
        self.server = server

    def new_page(self, **kw: object) -> object:
        ctx = self.browser.new_context(**kw)
        ctx.add_cookies(session_cookies(self.server.http, self.server.url))
        return ctx.new_page()

    def __getattr__(self, name: str) -> object:
        return getattr(self.browser, name)


@pytest.fixture(scope="module")
def raw_browser(chromium_path: str) -> Iterator[object]:
    """The Playwright Browser itself: new contexts are logged out (see harness.browser_login)."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        # The system chromium, never a downloaded one (`playwright install` is not used).
        b = p.chromium.launch(executable_path=chromium_path, args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture(scope="module")
def browser(raw_browser: object, server: Server) -> LoggedInBrowser:
    """new_page() gives a page logged in as the harness's educator."""
    return LoggedInBrowser(raw_browser, server)
