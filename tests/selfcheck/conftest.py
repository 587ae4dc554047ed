"""Fixtures for the self-check suite: the native checker and a running loop process."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="session")
def checker_exe() -> Path:
    from xrflab.selfcheck import checker_path

    return checker_path()


@pytest.fixture(scope="session")
def probe_exe(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from xrflab.build import build_project

    out = tmp_path_factory.mktemp("probe-build")
    return build_project(REPO / "tests/fixtures/loop_probe", build_dir=out, log=lambda line: None).executable


@pytest.fixture
def running_loop(probe_exe: Path, shm_name: str, tmp_path: Path):
    """The loop probe running on the simulated board with shared memory `shm_name`."""
    from xrflab.channels import Channels

    env = dict(os.environ, XRF_SHM=shm_name, XRF_TRANSPORT="sim", XRF_SIM="relbot")
    proc = subprocess.Popen(
        [str(probe_exe)], cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    deadline = time.monotonic() + 10
    ch = None
    while True:
        try:
            ch = Channels.open(shm_name, wait_s=0.5)
            if ch.info["pid"] == proc.pid and ch.status().running:
                break
            ch.close()
            ch = None
        except Exception:
            pass
        if proc.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"loop probe did not come up (exit {proc.returncode})")
        time.sleep(0.02)
    yield proc
    if proc.poll() is None:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=5)
    ch.close()
