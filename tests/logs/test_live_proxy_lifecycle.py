"""The live proxy's process (logs/rerun_servers.py LiveProxy, issue 30 item 4): it starts at the
run's first viewer; after its run has ended it stays while a viewer reads it or a viewer's page is
loading, and stops when neither; a viewer of the ended run starts it again. Real `rerun --serve-grpc` processes; the appliance's
read route (server/http/rerun.py) is what calls reader_joined/reader_left and expect_viewer
(through the appliance: tests/logs/test_live_stream.py::test_an_ended_runs_proxy_runs_only_while_watched)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from xrf_testing.harness import wait_for
from xrflab.logs import rerun_servers
from xrflab.logs.rerun_servers import LiveProxy

pytestmark = pytest.mark.live  # real rerun processes: not the fast tier


@pytest.fixture
def proxy() -> Iterator[LiveProxy]:
    p = LiveProxy.open_for_run(7, "alice")
    try:
        yield p
    finally:
        LiveProxy.stop_all()
    assert not p.running()


def test_it_starts_at_the_first_viewer(proxy: LiveProxy) -> None:
    """Nobody watched: no process (its recording sends nothing either, rerun_live.py). A live
    viewer's page starts it, on the port reserved with the run when that is still free."""
    assert not proxy.running() and proxy.local_url == f"rerun+http://127.0.0.1:{proxy.port}/proxy"
    proxy.expect_viewer()
    assert proxy.running() and proxy.watched()
    assert proxy.local_url == f"rerun+http://127.0.0.1:{proxy.port}/proxy"


def test_a_viewer_that_came_and_went_does_not_keep_an_ended_run(proxy: LiveProxy) -> None:
    """The page loaded (expect_viewer: its window is 20 s), connected, and left after the run's
    end: the process stops then, not when the loading window would have passed."""
    proxy.expect_viewer()
    proxy.reader_joined()
    proxy.run_ended()
    assert proxy.running(), "stopped while a viewer read it"
    proxy.reader_left()
    wait_for(lambda: not proxy.running(), timeout=5, what="the proxy to stop after its last viewer")
    assert LiveProxy.current() is proxy  # still the last run's: /api/logs/rerun shows it


def test_a_loading_viewer_keeps_it_until_its_window_passes(proxy: LiveProxy, monkeypatch) -> None:
    monkeypatch.setattr(rerun_servers, "EXPECT_VIEWER_S", 1.5)
    # expect_viewer starts the process as a connecting reader does (ensure_running), which keeps
    # it for CONNECT_GRACE_S (10 s) too: shortened like the loading window, or the wait below
    # timed out on a loaded machine, the stop coming 10 s + the process's end after the start
    # (CI, session 16).
    monkeypatch.setattr(rerun_servers, "CONNECT_GRACE_S", 1.0)
    proxy.expect_viewer()  # a page is loading and has not connected
    proxy.run_ended()
    assert proxy.running(), "stopped while a viewer's page was loading"
    wait_for(lambda: not proxy.running(), timeout=10, what="the proxy to stop after the loading window")


def test_a_viewer_of_the_ended_run_starts_it_again(proxy: LiveProxy) -> None:
    proxy.run_ended()
    wait_for(lambda: not proxy.running(), timeout=5, what="the unwatched ended run's proxy to stop")
    port = proxy.port
    assert proxy.ensure_running() and proxy.running()
    assert proxy.port == port and proxy.read_url == f"http://127.0.0.1:{port}"  # the same place when free
    proxy.reader_joined()
    proxy.reader_left()
    wait_for(lambda: not proxy.running(), timeout=5, what="the restarted proxy to stop after its viewer")


def test_the_next_run_closes_it_for_good(proxy: LiveProxy) -> None:
    nxt = LiveProxy.open_for_run(8, "bob")
    assert proxy.closed and not proxy.running() and LiveProxy.current() is nxt
    assert not proxy.ensure_running() and not proxy.running()  # a late reader of the old one
