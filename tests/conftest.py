"""Fixtures of general use for every test suite; suite-specific ones live in sub-folder conftests."""

from __future__ import annotations

import os
import shutil
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


@pytest.fixture(scope="session", autouse=True)
def nothing_left_behind(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """The session fails if it leaves a process, a /dev/shm object or a file in the checkout
    behind (xrf_testing/leaks.py says how a process is known to be ours); what is found is
    reported, then removed."""
    from xrf_testing.leaks import MARKER, Snapshot

    marker = os.environ.setdefault(MARKER, uuid.uuid4().hex)  # inherited by every child from now on
    snapshot = Snapshot.take(marker, tmp_path_factory.getbasetemp(), REPO_ROOT)
    yield
    snapshot.reclaim_dds()
    left = snapshot.leftovers()
    if left:
        snapshot.clean()
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
