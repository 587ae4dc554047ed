"""Fixtures for the dashboard self-check API tests: a real appliance (simulated RELbot bench)."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "appliance"))
from harness import Server, shared_builds_root, start_server, stop_server  # noqa: E402


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    s = start_server(tmp_path_factory.mktemp("data"), shared_builds_root(), sim="relbot")
    yield s
    stop_server(s)
