"""Fixtures for the rt_core suites: built controllers and running loop processes."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path
from typing import Iterator

import pytest

from xrflab.build import build_project
from xrflab.channels import Channels

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="session")
def probe_exe(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("probe-build")
    return build_project(REPO / "tests/fixtures/loop_probe", build_dir=out, log=lambda line: None).executable


class LoopProcess:
    """A controller executable running as a real process on its own shared memory."""

    def __init__(self, exe: Path, shm: str, cwd: Path, **env: str) -> None:
        self.shm = shm
        full_env = dict(os.environ, XRF_SHM=shm, XRF_QUIET="0", **{k: str(v) for k, v in env.items()})
        self.proc = subprocess.Popen([str(exe)], cwd=cwd, env=full_env, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True)
        deadline = time.monotonic() + 10
        while True:
            try:
                self.ch = Channels.open(shm, wait_s=0.5)
                if self.ch.info["pid"] == self.proc.pid:
                    break
                self.ch.close()
            except Exception:
                pass
            if self.proc.poll() is not None or time.monotonic() > deadline:
                out = self.proc.communicate(timeout=5)[0]
                raise RuntimeError(f"loop did not come up (exit {self.proc.returncode}):\n{out}")
            time.sleep(0.02)

    def command(self, cmd: str | int, timeout: float = 2.0):
        return self.ch.wait_command(self.ch.send_command(cmd), timeout=timeout)

    def wait_state(self, name: str, timeout: float = 3.0) -> None:
        deadline = time.monotonic() + timeout
        while self.ch.status().state_name != name:
            if time.monotonic() > deadline:
                raise AssertionError(f"state {self.ch.status().state_name}, wanted {name}")
            time.sleep(0.005)

    def wait_cycles(self, n: int, timeout: float = 5.0) -> None:
        target = self.ch.status().cycles + n
        deadline = time.monotonic() + timeout
        while self.ch.status().cycles < target:
            if time.monotonic() > deadline:
                raise AssertionError("the loop stopped cycling")
            time.sleep(0.005)

    def finish(self, timeout: float = 10.0) -> tuple[int, str]:
        out = self.proc.communicate(timeout=timeout)[0]
        return self.proc.returncode, out

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.communicate(timeout=5)
        self.ch.close()


@pytest.fixture
def run_loop(shm_name: str, tmp_path: Path) -> Iterator:
    started: list[LoopProcess] = []

    def start(exe: Path, **env: str) -> LoopProcess:
        lp = LoopProcess(exe, shm_name, tmp_path, **env)
        started.append(lp)
        return lp

    yield start
    for lp in started:
        lp.stop()
