#!/usr/bin/env python3
"""Take the dashboard screenshot for the docs: a simulated RELbot running for a few seconds with
changing setpoints, captured by the system chromium. Usage: python tests/ui/screenshot.py [out.png]"""

from __future__ import annotations

import shutil
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO_ROOT = HERE.parents[1]
# A program (`python tests/ui/screenshot.py`), not run by pytest: pyproject's pythonpath does not
# apply, so this checkout's appliance/ and the test helpers are put first here.
sys.path.insert(0, str(REPO_ROOT / "appliance"))
sys.path.insert(0, str(REPO_ROOT / "tests"))

from playwright.sync_api import sync_playwright  # noqa: E402

from xrf_testing.harness import CHROMIUM_ARGS, session_cookies, shared_builds_root, start_server, stop_server  # noqa: E402


def main() -> None:
    out = Path(sys.argv[1] if len(sys.argv) > 1 else REPO_ROOT / "docs" / "images" / "dashboard.png")
    out.parent.mkdir(parents=True, exist_ok=True)
    chromium = shutil.which("chromium") or "/usr/bin/chromium"
    with tempfile.TemporaryDirectory() as data:
        server = start_server(Path(data), shared_builds_root())
        try:
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
                ctx = browser.new_context(viewport={"width": 1400, "height": 1000})
                ctx.add_cookies(session_cookies(server.http, server.url))  # logged in as the educator
                page = ctx.new_page()
                page.goto(server.url + "/")
                page.wait_for_selector("#build-select option[value=relbot]", state="attached")
                page.select_option("#build-select", "relbot")
                page.click("#btn-start-run")
                page.wait_for_function("document.getElementById('state-name').textContent === 'IDLE'", timeout=120_000)
                page.click("#commands [data-cmd=initialise]")
                page.wait_for_function("document.getElementById('state-name').textContent === 'INITIALISED'")
                page.click("#commands [data-cmd=start]")
                page.wait_for_function("document.getElementById('state-name').textContent === 'RUN'")
                # A drive pattern: forward, turn, back, so the plots have something to show.
                for left, right in ((2, 2), (4, 2.5), (3, 1), (1, 1.5)):
                    page.fill("#sp-range-steer_left", str(left))
                    page.fill("#sp-range-steer_right", str(right))
                    time.sleep(2.0)  # the point: a stretch of driving for the plots to show
                page.click("#btn-clear")
                time.sleep(1.5)  # the point: the plots refill after the clear
                page.evaluate("window.scrollTo(0, 0)")  # the sticky bar belongs at the top
                page.screenshot(path=str(out), full_page=True)
                browser.close()
        finally:
            stop_server(server)
    print(out)


if __name__ == "__main__":
    main()
