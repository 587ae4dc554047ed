"""A project in each XRF2 release's style (tests/fixtures/xrf2_v1_0_project: ros_data /
xeno_data, main.cpp at the top, the framework in ../ros2-xenomai4-framework;
tests/fixtures/xrf2_v1_1_project: ros_msg / xeno_msg, sources named one by one, one in a
subfolder) is built unchanged by `xrf build`, runs on the simulated RELbot and is driven to RUN
and to its wheel setpoints with that release's command and state names (`xrf pub Command`,
`xrf echo Xenomai_state` / `XenoCmd`, `XenoState`)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from xrf_testing.loops import open_when_ready

REPO = Path(__file__).resolve().parents[2]
FIXTURES = {"v1.0": REPO / "tests/fixtures/xrf2_v1_0_project", "v1.1": REPO / "tests/fixtures/xrf2_v1_1_project"}
TOPICS = {"v1.0": ("Command", "Xenomai_state"), "v1.1": ("XenoCmd", "XenoState")}


def xrf(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "xrflab.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=dict(os.environ, PYTHONPATH=str(REPO / "appliance")),
    )


def _state(shm: str, topic: str) -> int:
    r = xrf("echo", topic, "--count", "1", "--shm", shm, "--timeout", "5")
    assert r.returncode == 0, r.stdout + r.stderr
    return json.loads(r.stdout.splitlines()[0])["data"]


@pytest.mark.parametrize("release", list(FIXTURES))
def test_release_project_builds_unchanged_and_reaches_its_setpoints(
    release: str, tmp_path: Path, shm_name: str
) -> None:
    project = tmp_path / FIXTURES[release].name
    shutil.copytree(FIXTURES[release], project)
    r = xrf("build", str(project), timeout=600)
    assert r.returncode == 0, r.stderr[-4000:]
    exe = Path(r.stdout.strip().splitlines()[-1])
    log = r.stderr
    # XRF2's selection: what the project's CMakeLists.txt compiles, nothing else.
    stray = "old/Scratch.cpp" if release == "v1.0" else "experiments/Broken.cpp"
    assert f"left out: {stray}: not compiled by the project's CMakeLists.txt" in log, log[-3000:]
    if release == "v1.1":
        assert "taken:    src/util/Unwrap.cpp" in log, log[-3000:]
    assert "left out: package.xml" in log

    cmd_topic, state_topic = TOPICS[release]
    proc = subprocess.Popen(
        [str(exe)],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=dict(
            os.environ, XRF_SHM=shm_name, XRF_SIM="relbot", XRF_TRANSPORT="sim", XRF_PRIO="0", XRF_LOG_DIR=str(tmp_path)
        ),
    )
    try:
        ch = open_when_ready(shm_name, proc)
        assert _state(shm_name, state_topic) == 1
        for cmd, want in (("initialise", 3), ("data=2", 4)):  # a name, then the Int32 form
            r = xrf("pub", cmd_topic, cmd, "--shm", shm_name)
            assert r.returncode == 0 and "accepted" in r.stdout, r.stdout + r.stderr
            deadline = time.monotonic() + 5
            while (s := _state(shm_name, state_topic)) != want:
                assert time.monotonic() < deadline, f"state {s}, wanted {want}"
        r = xrf("pub", "Ros2Xeno", "setpoint_left=1.0", "setpoint_right=-0.5", "--shm", shm_name)
        assert r.returncode == 0, r.stderr
        deadline = time.monotonic() + 20
        while True:
            r = xrf("echo", "Xeno2Ros", "--count", "1", "--shm", shm_name, "--timeout", "5")
            sample = json.loads(r.stdout.splitlines()[0])
            # Written through the release's message names, published by the framework.
            if abs(sample["pos_left"] - 1.0) < 0.05 and abs(sample["pos_right"] + 0.5) < 0.05:
                assert sample["state"] == 4
                break
            assert time.monotonic() < deadline, f"the wheels did not reach the setpoints: {sample}"
            time.sleep(0.2)
        for cmd in ("stop", "quit"):
            r = xrf("pub", cmd_topic, cmd, "--shm", shm_name)
            assert r.returncode == 0 and "accepted" in r.stdout, r.stdout + r.stderr
        out = proc.communicate(timeout=20)[0]
        assert proc.returncode == 0, out
        assert "cycles" in out and "missed" in out
        ch.close()
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
            proc.communicate(timeout=5)
