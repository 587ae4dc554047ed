"""The terminal workflow of a ROS 2 user: `xrf run` in one terminal, `xrf cmd/state/pub/echo` from
another, against the RELbot example on the simulated robot."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def xrf(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "xrflab.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=dict(os.environ, PYTHONPATH=str(REPO / "appliance")),
    )


def test_cli_walk_against_a_running_example(tmp_path: Path, shm_name: str) -> None:
    project = tmp_path / "relbot"
    shutil.copytree(REPO / "student_projects/examples/relbot", project, ignore=shutil.ignore_patterns("build"))
    runner = subprocess.Popen(
        [sys.executable, "-m", "xrflab.cli", "run", str(project), "--sim", "relbot", "--shm", shm_name],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=dict(os.environ, PYTHONPATH=str(REPO / "appliance")),
    )
    try:
        r = xrf("state", "--shm", shm_name, "--wait", "IDLE", "--timeout", "120", timeout=150)
        assert r.returncode == 0, r.stdout + r.stderr

        r = xrf("cmd", "start", "--shm", shm_name)
        assert r.returncode == 3 and "rejected" in r.stdout and "not allowed in state IDLE" in r.stdout

        for cmd, state in [("initialise", "INITIALISED"), ("start", "RUN"), ("pause", "PAUSED"), ("start", "RUN")]:
            r = xrf("cmd", cmd, "--shm", shm_name)
            assert r.returncode == 0 and "accepted" in r.stdout, r.stdout + r.stderr
            r = xrf("state", "--shm", shm_name, "--wait", state, "--timeout", "5")
            assert r.returncode == 0, r.stdout + r.stderr

        r = xrf("pub", "Ros2Xeno", "steer_left=1.5", "steer_right=-0.5", "--shm", shm_name)
        assert r.returncode == 0, r.stdout + r.stderr
        deadline = time.monotonic() + 10
        while True:
            r = xrf("echo", "Xeno2Ros", "--count", "1", "--shm", shm_name)
            assert r.returncode == 0, r.stderr
            sample = json.loads(r.stdout.splitlines()[0])
            if abs(sample["pos_left"] - 1.5) < 0.05 and abs(sample["pos_right"] + 0.5) < 0.05:
                break
            assert time.monotonic() < deadline, f"Xeno2Ros did not follow the setpoint: {sample}"
            time.sleep(0.2)

        r = xrf("echo", "status", "--count", "1", "--shm", shm_name)
        assert json.loads(r.stdout.splitlines()[0])["state_name"] == "RUN"

        for cmd, _state in [("stop", "STOPPED"), ("quit", "QUIT")]:
            r = xrf("cmd", cmd, "--shm", shm_name)
            assert r.returncode == 0 and "accepted" in r.stdout, r.stdout + r.stderr
        out, _ = runner.communicate(timeout=20)
        assert runner.returncode == 0, out
        assert "cycles" in out and "missed" in out
    finally:
        if runner.poll() is None:
            runner.send_signal(signal.SIGKILL)
            runner.communicate(timeout=5)
