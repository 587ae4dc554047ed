"""Fixtures for the installer tests; the helpers are in deploy_support.py (a unique module name,
so `import` never picks up another suite's conftest). And the fresh-machine check's place in the
session: its tests run last, and when the session has other tests too, its run starts in the
background with the session's first test (fresh_background.py) and overlaps them."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from xrf_testing.deploy_support import fresh_root, source_snapshot
from xrf_testing.fresh_background import BACKGROUND, Background

FRESH_MODULE = Path(__file__).resolve().parent / "test_fresh_machine.py"


def _is_fresh(item: pytest.Item) -> bool:
    return item.path == FRESH_MODULE


@pytest.hookimpl(trylast=True)  # after --ff/--lf and any other reordering
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The fresh-machine check's tests last: they wait for its run, which overlaps everything before."""
    items[:] = [i for i in items if not _is_fresh(i)] + [i for i in items if _is_fresh(i)]


def pytest_collection_finish(session: pytest.Session) -> None:
    if hasattr(session.config, "workerinput"):
        return  # an xdist worker: the controller runs the check in the background (fresh_background.py)
    fresh = [i for i in session.items if _is_fresh(i)]
    if not fresh or len(fresh) == len(session.items) or os.geteuid() != 0:
        return  # alone, the check runs in its fixture as it always did; not root, it skips
    if not all(shutil.which(t) for t in ("unshare", "pivot_root", "nice", "ionice")):
        return  # the fixture says which is missing
    background = Background(session.config)
    session.config.stash[BACKGROUND] = background
    session.config.pluginmanager.register(background, "xrf-fresh-machine-background")


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
