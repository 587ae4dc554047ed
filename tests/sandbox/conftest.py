"""Fixtures for the run-sandbox tests: a real appliance whose data folder the build user can
reach, and student accounts."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest

from xrf_testing.harness import Server, shared_builds_root, start_server, stop_server
from xrf_testing.projects_support import reachable_tmp

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def data_dir() -> Iterator[Path]:
    d = reachable_tmp("sandbox")
    yield d
    shutil.rmtree(d, ignore_errors=True)


@pytest.fixture(scope="module")
def server(data_dir: Path) -> Iterator[Server]:
    s = start_server(data_dir, shared_builds_root())
    yield s
    stop_server(s)
