"""Fixtures for the log suites: a table of edge values for all six types (reader, converter), and
an appliance with the loop probe for the logging tests through the appliance (helpers:
xrf_testing/logs_support.py)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from xrf_testing.harness import stop_server
from xrf_testing.log_cases import VARIABLES, edge_rows
from xrf_testing.logs_support import REPO, Server, start
from xrf_testing.loops import build_probe
from xrf_testing.writers import xrflog_segment


@pytest.fixture
def edge_file(tmp_path: Path) -> Path:
    path = tmp_path / "edge.xrf"
    path.write_bytes(xrflog_segment(VARIABLES, edge_rows()))
    return path


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    s = start(tmp_path_factory.mktemp("data"))
    yield s
    stop_server(s)


@pytest.fixture(scope="module")
def probe() -> Path:
    """The loop probe, built once into the repository's cache (shared with the appliance's runs)."""
    return build_probe(REPO / ".cache" / "logs-appliance-builds" / "probe")
