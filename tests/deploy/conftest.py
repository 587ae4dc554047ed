"""Fixtures for the installer tests; the helpers are in deploy_support.py (a unique module name,
so `import` never picks up another suite's conftest)."""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from deploy_support import fresh_root, source_snapshot  # noqa: E402


def requirements_or_skip() -> None:
    if os.geteuid() != 0:
        pytest.skip("installer tests need root (chroot, useradd)")


@pytest.fixture(scope="module")
def debian_root(tmp_path_factory):
    requirements_or_skip()
    root = fresh_root(tmp_path_factory.mktemp("deploy") / "root")
    yield root
    shutil.rmtree(root, ignore_errors=True)  # 700 MB; pytest keeps its last tmp folders


@pytest.fixture(scope="module")
def source(tmp_path_factory) -> Path:
    return source_snapshot(tmp_path_factory.mktemp("source") / "xrf-lab")
