"""Fixtures of general use for every test suite; suite-specific ones live in sub-folder conftests."""

from __future__ import annotations

import os
import shutil
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]

# The fast tier (--fast, the `live` mark): which tests start processes, read from their code.
pytest_plugins = ["xrf_testing.tiers"]

# pyproject.toml's `pythonpath = ["appliance", "tests"]` puts this checkout's appliance/ first
# (a clone under /tmp tests its own code, not the editable install's) and makes the shared test
# helpers importable as `xrf_testing`; no test changes sys.path itself.

try:
    from hypothesis import settings
    from hypothesis.database import DirectoryBasedExampleDatabase

    # Keep hypothesis' example database in the ignored .cache/ folder, not in the repo root.
    settings.register_profile("xrf", database=DirectoryBasedExampleDatabase(str(REPO_ROOT / ".cache" / "hypothesis")))
    settings.load_profile("xrf")
except ImportError:  # hypothesis is a test extra; suites that need it import it themselves
    pass


def _xdist_worker(config: pytest.Config) -> bool:
    return hasattr(config, "workerinput")


def _xdist_controller(config: pytest.Config) -> bool:
    """The process that hands tests to pytest-xdist's workers (`./lab test`, the whole suite, runs
    `-n`): it runs no test and outlives every worker."""
    return not _xdist_worker(config) and bool(getattr(config.option, "numprocesses", None))


LEAK_SNAPSHOT = pytest.StashKey[object]()
SHARED_FRESH = pytest.StashKey[object]()


def _take_snapshot(config: pytest.Config, temp_root: Path) -> object:
    from xrf_testing.leaks import MARKER, Snapshot

    marker = os.environ.setdefault(MARKER, uuid.uuid4().hex)  # inherited by every child from now on
    return Snapshot.take(marker, temp_root, REPO_ROOT)


def _leftovers(snapshot) -> list[str]:
    snapshot.reclaim_by_design()
    left = snapshot.leftovers()
    if left:
        snapshot.clean()
    return left


@pytest.hookimpl(tryfirst=True)  # before xdist starts its workers (they inherit the marker)
def pytest_sessionstart(session: pytest.Session) -> None:
    """With workers (xdist) the leak check belongs to the controller: a worker ending early would
    see the other worker's live servers, segments and files as its own leftovers, and remove them."""
    config = session.config
    if _xdist_controller(config):
        config.stash[LEAK_SNAPSHOT] = _take_snapshot(config, config._tmp_path_factory.getbasetemp())
        # after the snapshot, so that the leak check sees the run too (fresh_background.py)
        from xrf_testing.fresh_background import start_shared

        config.stash[SHARED_FRESH] = start_shared(config)


@pytest.hookimpl(wrapper=True)
def pytest_sessionfinish(session: pytest.Session):
    result = yield  # every other finish first: xdist's workers are gone after it
    fresh = session.config.stash.get(SHARED_FRESH, None)
    if fresh is not None:
        fresh.close()  # killed if its tests were never reached, and its 2 GB tree removed
    snapshot = session.config.stash.get(LEAK_SNAPSHOT, None)
    if snapshot is not None:
        left = _leftovers(snapshot)
        if left:
            sys.stderr.write("\nthe test session left behind:\n  " + "\n  ".join(left) + "\n")
            session.exitstatus = pytest.ExitCode.TESTS_FAILED
    return result


@pytest.fixture(scope="session", autouse=True)
def nothing_left_behind(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """The session fails if it leaves a process, a /dev/shm object or a file in the checkout
    behind (xrf_testing/leaks.py says how a process is known to be ours); what is found is
    reported, then removed. Under xdist the controller checks instead (pytest_sessionstart)."""
    if _xdist_worker(request.config):
        yield
        return
    snapshot = _take_snapshot(request.config, tmp_path_factory.getbasetemp())
    yield
    left = _leftovers(snapshot)
    if left:
        pytest.fail("the test session left behind:\n  " + "\n  ".join(left), pytrace=False)


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO_ROOT


@pytest.fixture
def shm_name() -> str:
    """A shared-memory name unique to this test; /dev/shm/<name> is removed afterwards."""
    name = f"xrf-test-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    yield name
    try:
        (Path("/dev/shm") / name).unlink()
    except FileNotFoundError:
        pass


@pytest.fixture(scope="session")
def chromium_path() -> str:
    """The system Chromium for browser tests. Missing is a failure, never a skip: the UI must
    be tested wherever the suite runs (./lab installs Chromium and exports XRF_CHROMIUM)."""
    candidates = [os.environ.get("XRF_CHROMIUM", "")]
    candidates += [shutil.which(n) or "" for n in ("chromium", "chromium-browser", "google-chrome")]
    for path in candidates:
        if path and os.access(path, os.X_OK):
            return path
    pytest.fail("no Chromium found (set XRF_CHROMIUM or install the 'chromium' package): UI tests cannot run")
