"""The Runs page's downloads in a real browser (issue 31, friction): the heading's "logs: raw ·
CSV · MAT · Parquet · rerun" looked like links and was not, and a run's downloads appeared only
after clicking its row, with nothing saying so. Every run row now has a real control for its log
files, and what it opens are real download links (the existing routes: the same permissions)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from xrf_testing.harness import Server, shared_builds_root, start_server, stop_server, wait_for
from xrf_testing.logs_support import PROBE, REPO, projects_dir


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    s = start_server(tmp_path_factory.mktemp("data"), shared_builds_root(), projects_dir=str(projects_dir()))
    yield s
    stop_server(s)


def test_each_run_row_opens_its_download_links(server: Server, browser) -> None:  # noqa: ANN001
    run = server.start_run(PROBE)
    for cmd in ("initialise", "start"):
        assert server.http.post("/api/runs/current/command", json={"cmd": cmd}).json()["accepted"]
    wait_for(
        lambda: server.http.get(f"/api/logs/runs/{run['id']}").json()["run"]["log_records"] > 0,
        what="the probe's first log records",
    )
    server.stop_run()
    name = server.http.get(f"/api/logs/runs/{run['id']}").json()["files"][0]["name"]

    page = browser.new_page(accept_downloads=True, viewport={"width": 1400, "height": 700})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(server.url + "/#runs")
    row = page.locator(f"#runs-row-{run['id']}")
    row.wait_for(timeout=15000)
    # The heading does not list the formats as if they were links; it says what to click.
    heading = page.inner_text("#panel-runs h2")
    assert "click" in heading.lower(), heading
    assert page.locator("#panel-runs h2 a").count() == 0  # no link-looking text in it either

    # The row has a control of its own for its logs (a real button, not text).
    control = row.get_by_role("button")
    assert control.count() == 1, row.inner_html()
    control.click()
    links = page.locator("#rl-files a.dl[download]")
    links.first.wait_for(timeout=10000)
    fmts = [links.nth(i).get_attribute("data-fmt") for i in range(links.count())]
    assert {"raw", "csv", "mat", "parquet", "rrd"} <= set(fmts), fmts
    href = page.get_attribute('#rl-files a.dl[data-fmt="csv"]', "href")
    assert href is not None and href.startswith(f"/api/logs/runs/{run['id']}/files/"), href
    # the files are in view after the click, not somewhere below the fold
    box = page.locator("#panel-run-logs").bounding_box()
    assert box is not None and box["y"] < 700, box
    (REPO / "test-results").mkdir(exist_ok=True)
    page.screenshot(path=str(REPO / "test-results" / "runs-downloads.png"))  # for a person to look at
    with page.expect_download() as dl:
        page.click('#rl-files a.dl[data-fmt="csv"]')
    assert dl.value.suggested_filename == f"run{run['id']}_{Path(name).stem}.csv"
    assert dl.value.failure() is None
    assert not errors, errors
    page.context.close()
