"""Fixtures for the ROS 2 bridge tests: real rclpy, real loop processes, real DDS on loopback;
and for the bridge run by the appliance: a real appliance (xrf_testing/harness.py) that spawns the
real bridge for a real relbot loop, and a separate rclpy node process (ros_cmd_peer.py).

Nothing is skipped: without rclpy (pip install ros-rclpy ros-std-msgs ros-rmw-fastrtps-cpp and
the interface-build set, see docs/ros2/bridge.md) every test here fails with that message.
"""

from __future__ import annotations

import json
import os
import selectors
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from xrf_testing.harness import Server, shared_builds_root, start_server, stop_server
from xrf_testing.loops import open_when_ready
from xrf_testing.ros import isolated_ros_env, require_rclpy
from xrflab.build import build_project

REPO = Path(__file__).resolve().parents[2]
PEER = Path(__file__).with_name("ros_peer.py")
CMD_PEER = Path(__file__).with_name("ros_cmd_peer.py")  # the node the appliance's bridge talks to
RELBOT = REPO / "student_projects/examples/relbot"
PROBE = REPO / "bench/ros/probe_project"

# One DDS domain per test run (1..100; the appliance's bridge tests use 101..200), on loopback only.
ROS_ENV = isolated_ros_env(1, 100)


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "ros: ROS 2 bridge tests (real rclpy; about a minute, one of them a 15 s soak)")


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


# The bridge run by the appliance (test_ros_appliance.py).


@pytest.fixture(scope="module")
def ros_domain() -> dict[str, str]:
    require_rclpy()
    # Loopback only, a random domain: the appliance (and the bridge it spawns) inherit these.
    env = isolated_ros_env(101, 200)
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    yield env
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory, ros_domain: dict[str, str]) -> Iterator[Server]:
    s = start_server(tmp_path_factory.mktemp("data"), shared_builds_root())
    yield s
    stop_server(s)


class Peer:
    """The rclpy node process; each request is a line on its stdin, answered by a JSON line."""

    def __init__(self, log: Path) -> None:
        self.log_path = log
        self._err = open(log, "w")
        self.proc = subprocess.Popen(
            [sys.executable, str(CMD_PEER)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._err,
            text=True,
            bufsize=1,
        )
        assert self.ask("", 30).get("hello"), "peer did not start"

    def ask(self, line: str, timeout: float) -> dict[str, Any]:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        if line:
            self.proc.stdin.write(line + "\n")
            self.proc.stdin.flush()
        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        if not sel.select(timeout + 10):
            raise AssertionError(f"peer gave no answer to {line!r}:\n{self.log_path.read_text()}")
        reply = self.proc.stdout.readline()
        if not reply:
            raise AssertionError(f"peer ended (exit {self.proc.poll()}):\n{self.log_path.read_text()}")
        return json.loads(reply)

    def close(self) -> None:
        if self.proc.poll() is None:
            assert self.proc.stdin is not None
            self.proc.stdin.close()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._err.close()


@pytest.fixture
def peer(tmp_path: Path, ros_domain: dict[str, str]) -> Iterator[Peer]:
    p = Peer(tmp_path / "peer.log")
    yield p
    p.close()
