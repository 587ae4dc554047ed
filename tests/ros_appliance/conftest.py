"""Fixtures for the ROS 2 bridge run by the appliance: a real appliance (tests/appliance/harness)
that spawns the real bridge for a real relbot loop, and a separate rclpy node process.

Nothing is skipped: without rclpy every test here fails with the install command.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "appliance"))
from harness import Server, shared_builds_root, start_server, stop_server  # noqa: E402

from xrf_testing.ros import isolated_ros_env, require_rclpy  # noqa: E402

PEER = HERE / "ros_cmd_peer.py"


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "ros: ROS 2 bridge tests (real rclpy)")


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
            [sys.executable, str(PEER)],
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
        import selectors

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
