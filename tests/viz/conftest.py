"""Fixtures for the 3D view's server tests: one real appliance (subprocess) per module."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from xrf_testing.harness import Server, shared_builds_root, start_server, stop_server


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    # On every interface, as on a Pi: viser must still listen on 127.0.0.1 only (test_viz_server)
    s = start_server(tmp_path_factory.mktemp("data"), shared_builds_root(), host="0.0.0.0")
    yield s
    stop_server(s)
