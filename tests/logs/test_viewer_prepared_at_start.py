"""The rerun viewer's files are prepared at the appliance's start (Settings.prepare_viewer_at_start,
server/app.py; issue 30 item 4): a practical's first live viewer no longer has the preparing child
(~100 MB with its `rerun --serve-web`) beside the appliance, its run and the run's recording."""

from __future__ import annotations

import importlib.metadata
import os
from pathlib import Path

from xrf_testing.harness import shared_builds_root, start_server, stop_server, wait_for
from xrflab.server.http.rerun import PREPARED_AS

PREPARE_S = 300  # the copy gzips a 43 MB wasm: seconds here, longer on a loaded CI host


def _viewer_folder(data: Path) -> Path:
    return data / "rerun-viewer" / f"{importlib.metadata.version('rerun-sdk')}-{PREPARED_AS}"


def _children_in(data: Path) -> list[int]:
    """Processes whose command line names a folder under `data` (the preparing child's does)."""
    found = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                if str(data).encode() in f.read():
                    found.append(int(pid))
        except OSError:
            continue
    return found


def test_the_viewer_is_prepared_at_start_and_served_from_there(tmp_path: Path) -> None:
    data = tmp_path / "data"
    server = start_server(data, shared_builds_root(), prepare_viewer_at_start=True)
    try:
        ready = _viewer_folder(data) / "ready"
        wait_for(ready.is_file, timeout=PREPARE_S, what="the viewer prepared at the appliance's start")
        prepared = ready.stat().st_mtime_ns
        page = server.http.get("/rerun/index.html")
        assert page.status_code == 200 and b"<html" in page.content.lower()
        assert ready.stat().st_mtime_ns == prepared  # served from the start's copy, not prepared again
    finally:
        stop_server(server)


def test_a_stop_while_preparing_leaves_no_child_and_no_half_copy(tmp_path: Path) -> None:
    data = tmp_path / "data"
    server = start_server(data, shared_builds_root(), prepare_viewer_at_start=True)
    stopped = False
    try:
        # the preparing child at work: its half-made copy (`.<version>-<as>.<pid>.part`) exists
        wait_for(
            lambda: any(p.name.endswith(".part") for p in (data / "rerun-viewer").glob(".*")),
            timeout=60,
            what="the preparation under way",
        )
        assert _children_in(data), "no preparing child"
        stop_server(server)
        stopped = True
        wait_for(lambda: not _children_in(data), timeout=20, what="the preparing child gone with the appliance")
        assert not list((data / "rerun-viewer").glob(".*.part")), "a half-made copy was left"
        assert not _viewer_folder(data).exists(), "an unfinished copy looks prepared"
    finally:
        if not stopped:
            stop_server(server)
