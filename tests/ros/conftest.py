"""Fixtures for the ROS 2 bridge tests: real rclpy, real loop processes, real DDS on loopback.

Nothing is skipped: without rclpy (pip install ros-rclpy ros-std-msgs ros-rmw-fastrtps-cpp and
the interface-build set, see docs/ros2/bridge.md) every test here fails with that message.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from xrf_testing.loops import open_when_ready
from xrf_testing.ros import isolated_ros_env, require_rclpy
from xrflab.build import build_project

REPO = Path(__file__).resolve().parents[2]
PEER = Path(__file__).with_name("ros_peer.py")
RELBOT = REPO / "student_projects/examples/relbot"
PROBE = REPO / "bench/ros/probe_project"

# One DDS domain per test run (1..100; the appliance suite uses 101..200), on loopback only.
ROS_ENV = isolated_ros_env(1, 100)


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "ros: ROS 2 bridge tests (real rclpy; about 1.5 minutes, one of them 60 s)")


@pytest.fixture(scope="session")
def ros_env() -> dict[str, str]:
    require_rclpy()
    os.environ.update(ROS_ENV)  # for in-process nodes
    return dict(ROS_ENV)


@pytest.fixture(scope="session")
def relbot_exe(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_project(RELBOT, build_dir=tmp_path_factory.mktemp("relbot"), log=lambda line: None).executable


@pytest.fixture(scope="session")
def probe_exe(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_project(PROBE, build_dir=tmp_path_factory.mktemp("ros-probe"), log=lambda line: None).executable


def msgs_env(msg_dir: Path) -> dict[str, str]:
    """What a course node's shell would have after sourcing the interface package."""
    from xrflab.ros.interfaces import build_interface_package, runtime_env

    return runtime_env(build_interface_package(msg_dir))


class Proc:
    """A child process with output in a file; stopped with SIGTERM, then SIGKILL."""

    def __init__(self, argv: list[str], log: Path, env: dict[str, str], cwd: Path | None = None) -> None:
        self.log_path = log
        self._log = open(log, "w")
        self.proc = subprocess.Popen(argv, env=env, cwd=cwd, stdout=self._log, stderr=subprocess.STDOUT, text=True)

    @property
    def output(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text()

    def terminate(self, timeout: float = 10.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
                self._log.close()
                raise AssertionError(
                    f"{self.proc.args[:3]} ignored SIGTERM for {timeout:g} s:\n{self.output}"
                ) from None
        self._log.close()
        return self.proc.returncode


class Loop(Proc):
    def __init__(self, exe: Path, shm: str, workdir: Path, **env: str) -> None:
        full = dict(os.environ, XRF_SHM=shm, XRF_SIM="relbot", XRF_TRANSPORT="sim", XRF_QUIET="1", **env)
        super().__init__([str(exe)], workdir / f"loop-{shm}.log", full, cwd=workdir)
        try:
            self.ch = open_when_ready(shm, self.proc)
        except RuntimeError as exc:
            raise RuntimeError(f"{exc}:\n{self.output}") from None

    def command(self, cmd: str):
        return self.ch.wait_command(self.ch.send_command(cmd), timeout=2.0)


def bridge_argv(shm: str, *extra: str) -> list[str]:
    return [sys.executable, "-m", "xrflab.ros.bridge", "--shm", shm, *extra]


@pytest.fixture
def procs(tmp_path: Path, ros_env: dict[str, str]) -> Iterator:
    started: list[Proc] = []

    class Starter:
        workdir = tmp_path

        def loop(self, exe: Path, shm: str, **env: str) -> Loop:
            lp = Loop(exe, shm, tmp_path, **env)
            started.append(lp)
            return lp

        def bridge(self, shm: str, *extra: str) -> Proc:
            env = dict(os.environ, **ros_env, PYTHONPATH=str(REPO / "appliance"))
            p = Proc(bridge_argv(shm, *extra), tmp_path / f"bridge-{shm}.log", env)
            started.append(p)
            return p

        def peer(self, msg_dir: Path, *args: str, timeout: float) -> tuple[int, str]:
            env = dict(os.environ, **ros_env, **msgs_env(msg_dir))
            r = subprocess.run(
                [sys.executable, str(PEER), *args], env=env, capture_output=True, text=True, timeout=timeout
            )
            return r.returncode, r.stdout + r.stderr

    yield Starter()
    for p in reversed(started):
        if p.proc.poll() is None:
            p.proc.kill()
            p.proc.wait(5)
