"""Fixtures for the logging tests through the appliance (helpers: logs_support.py)."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from harness import stop_server  # noqa: E402
from logs_support import REPO, Server, start  # noqa: E402

from xrf_testing.loops import build_probe  # noqa: E402


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    s = start(tmp_path_factory.mktemp("data"))
    yield s
    stop_server(s)


@pytest.fixture(scope="module")
def probe() -> Path:
    """The loop probe, built once into the repository's cache (shared with the appliance's runs)."""
    return build_probe(REPO / ".cache" / "logs-appliance-builds" / "probe")
