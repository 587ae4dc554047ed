"""Fixtures: a data folder the build user can reach (not under /tmp/pytest-of-root, which is
private to root), a Builder for sandbox tests, an appliance for the API tests."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest

from xrf_testing.projects_support import reachable_tmp


@pytest.fixture
def data_dir() -> Iterator[Path]:
    d = reachable_tmp("data")
    yield d
    shutil.rmtree(d, ignore_errors=True)


@pytest.fixture(scope="module")
def module_data_dir() -> Iterator[Path]:
    d = reachable_tmp("data")
    yield d
    shutil.rmtree(d, ignore_errors=True)
