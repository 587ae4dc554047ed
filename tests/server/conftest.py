"""Fixtures for the appliance tests: a real server per module, real relbot runs."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from xrf_testing.harness import Server, shared_builds_root, start_server, stop_server


@pytest.fixture(scope="session")
def builds_root() -> Path:
    return shared_builds_root()


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory, builds_root: Path) -> Iterator[Server]:
    s = start_server(tmp_path_factory.mktemp("data"), builds_root)
    yield s
    stop_server(s)


@pytest.fixture
def running(server: Server) -> Iterator[dict[str, Any]]:
    """A relbot run in IDLE; ended after the test whatever happened."""
    server.stop_run()
    run = server.start_run("relbot")
    yield run
    server.stop_run()
