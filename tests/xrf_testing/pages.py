"""A dashboard page in the browser tests: opened, connected, its script errors collected and asserted
empty at the end, closed with its run stopped whatever the test did (one definition for every UI test
that drives a run)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from .harness import Server

CONNECTED = "document.getElementById('conn').textContent === 'connected'"


@contextmanager
def dashboard_page(
    server: Server, browser: Any, path: str = "/", width: int = 1400, height: int = 1000
) -> Iterator[Any]:
    """The dashboard at ``path`` with no run left from an earlier test; on a clean exit, no script
    error was thrown while the test drove it."""
    server.stop_run()
    page = browser.new_page(viewport={"width": width, "height": height})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        page.goto(server.url + path)
        page.wait_for_function(CONNECTED)
        yield page
        assert not errors, errors
    finally:
        page.context.close()
        server.stop_run()
