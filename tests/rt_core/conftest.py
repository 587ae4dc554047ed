"""Fixtures for the rt_core suites: built controllers and running loop processes."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from xrf_testing.loops import LoopProcess, build_probe


@pytest.fixture(scope="session")
def probe_exe(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_probe(tmp_path_factory.mktemp("probe-build"))


@pytest.fixture
def run_loop(shm_name: str, tmp_path: Path) -> Iterator:
    started: list[LoopProcess] = []

    def start(exe: Path, **env: str) -> LoopProcess:
        lp = LoopProcess(exe, shm_name, tmp_path, XRF_QUIET="0", **env)
        started.append(lp)
        return lp

    yield start
    for lp in started:
        lp.stop()
