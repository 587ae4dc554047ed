"""The Runs page in a real browser: the run list with its logging figures and lost badge, a CSV
download through the browser (Playwright's download API) equal to `xrf decode`'s CSV, and the
rerun viewer embedded from the appliance."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "appliance"))
from harness import Server, shared_builds_root, start_server, stop_server  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
PROBE = "logs-probe"


def _projects() -> Path:
    root = REPO / ".cache" / "logs-appliance-projects" / "examples"
    root.mkdir(parents=True, exist_ok=True)
    link = root / PROBE
    if not link.is_symlink():
        link.symlink_to(REPO / "tests/fixtures/loop_probe")
    return root.parent


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    s = start_server(tmp_path_factory.mktemp("data"), shared_builds_root(), projects_dir=str(_projects()))
    yield s
    stop_server(s)


def test_runs_page_lists_runs_and_downloads_a_csv(server: Server, browser, tmp_path: Path) -> None:
    run = server.start_run(PROBE)
    for cmd in ("initialise", "start"):
        assert server.http.post("/api/runs/current/command", json={"cmd": cmd}).json()["accepted"]
    time.sleep(0.5)
    server.stop_run()
    info = server.http.get(f"/api/logs/runs/{run['id']}").json()
    name = info["files"][0]["name"]

    page = browser.new_page(accept_downloads=True)
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
    subprocess.run([sys.executable, "-m", "xrflab.cli", "decode", str(server.data_dir / "runs" / str(run["id"]) / name),
                    "--to", "csv", "-o", str(want)], check=True, env=env, capture_output=True)
    assert got.read_bytes() == want.read_bytes()
    assert got.read_text().count("\n") == info["files"][0]["records"] + 1
    # The rerun viewer is embedded from the appliance (not a CDN), pointed at this host.
    src = page.locator("#rr-frame").get_attribute("src")
    assert src.startswith("/rerun/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A")
    page.locator(".open-rrd").first.click()
    page.wait_for_function("document.querySelector('#rr-frame').getAttribute('src').includes('fmt%3Drrd')")
    page.close()
