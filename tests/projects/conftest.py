"""Fixtures: a data folder the build user can reach (not under /tmp/pytest-of-root, which is
private to root), a Builder for sandbox tests, an appliance for the API tests."""

from __future__ import annotations

import shutil
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from projects_support import reachable_tmp

REPO = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent
for p in (REPO / "appliance", REPO / "tests" / "appliance", HERE):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))


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
