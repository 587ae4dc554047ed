"""The youBot example and template (issue 29 item 3) on the simulated youBot, real processes: all
four states. INITIALISING raises the arm from its rest pose to the ready pose and `start` is
refused until it is there; a base command before then is refused (`base_refused`, the base does
not move); STOPPING lowers the arm onto its rest stops at a bounded speed and only then ends.

In RUN, once ready, the base drives: its wheels are channels 6..9, on the bench's second and third
ico boards (sample_more / actuate_more), so the base moving is the framework exchanging them."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from xrf_testing.loops import LoopProcess
from xrflab.build import build_project

REPO = Path(__file__).resolve().parents[2]
PROJECTS = {
    "example": REPO / "student_projects/examples/youbot",
    "template": REPO / "student_projects/templates/youbot",
}
DEG = math.pi / 180
# The example's poses (src/YoubotController.cpp) and the plant's rest (plant_youbot.c): J1..J4.
READY = [0.0, 10 * DEG, 60 * DEG, 40 * DEG]
REST = [0.0, -65 * DEG, 151 * DEG, -102.5 * DEG]
# Rising at 30 °/s, J4 travels 142.5°: about 5 s, plus settling; lowering at 20 °/s: about 7 s.
MOVE_S = 20.0
# The closing sequence's bound, 20 °/s per joint, with room for the PID's lag and the sampling.
CLOSING_MAX = 30 * DEG


@pytest.fixture(scope="module", params=list(PROJECTS))
def exe(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp(f"youbot-{request.param}")
    return build_project(PROJECTS[request.param], out, log=lambda _l: None).executable


@pytest.fixture
def youbot(exe: Path, shm_name: str, tmp_path: Path) -> Iterator[LoopProcess]:
    lp = LoopProcess(exe, shm_name, tmp_path, XRF_TRANSPORT="sim", XRF_SIM="youbot", XRF_MAX_CYCLES="120000")
    yield lp
    lp.stop()


def joints(lp: LoopProcess) -> list[float]:
    return [float(lp.ch.shm.sim.plant[i]) for i in range(4)]


def base(lp: LoopProcess) -> list[float]:
    return [float(lp.ch.shm.sim.plant[i]) for i in range(5, 8)]


def xeno2ros(lp: LoopProcess, reader, last: dict) -> dict:
    for t in reader.read():
        if t.xeno2ros:
            last.update(t.xeno2ros)
    return last


def test_ready_pose_before_run_base_refused_and_closing_sequence(
    youbot: LoopProcess, request: pytest.FixtureRequest
) -> None:
    lp = youbot
    drives_base = request.node.callspec.params["exe"] == "example"  # the template leaves it to the student
    reader, seen = lp.ch.telemetry_reader(), {}
    assert joints(lp) == pytest.approx(REST, abs=0.5 * DEG)  # parked at rest at power-up
    lp.command("initialise", "INITIALISING")
    # A base command while the arm rises: refused, and the base stays where it is.
    lp.ch.write_ros2xeno({"base_vx": 0.1, "base_wz": 0.2})
    deadline = time.monotonic() + MOVE_S
    refused = False
    while lp.ch.status().state_name == "INITIALISING":
        assert time.monotonic() < deadline, f"the arm never got ready: {joints(lp)}"
        r = lp.command("start")
        assert not r.accepted or lp.ch.status().state_name != "INITIALISING", "start taken while rising"
        v = xeno2ros(lp, reader, seen)
        if v:
            assert v["arm_ready"] is False or lp.ch.status().state_name != "INITIALISING", v
            refused = refused or v["base_refused"] is True
        time.sleep(0.05)  # polling while the arm rises
    assert lp.ch.status().state_name == "INITIALISED"
    assert refused, "the base command before ready was not reported refused"
    assert base(lp) == [0.0, 0.0, 0.0]
    assert joints(lp) == pytest.approx(READY, abs=2.5 * DEG)
    deadline = time.monotonic() + 2.0
    while xeno2ros(lp, reader, seen).get("arm_ready") is not True:
        assert time.monotonic() < deadline, f"arm_ready never reported: {seen}"
        time.sleep(0.02)  # polling the telemetry for the flag
    lp.command("start", "RUN")
    if drives_base:
        # Ready: the base command is taken; the wheels (boards 1 and 2) move it forward.
        lp.ch.write_ros2xeno({"base_vx": 0.1, "base_wz": 0.0})
        deadline = time.monotonic() + 10.0
        while base(lp)[0] < 0.05:
            assert time.monotonic() < deadline, f"the base did not drive: {base(lp)}"
            time.sleep(0.05)  # polling the plant's odometry
        wheel_pwm = [t.pwm[5:9] for t in reader.read()]
        assert wheel_pwm and any(any(p) for p in wheel_pwm), "no wheel PWM in the telemetry (channels 6..9)"
    lp.ch.write_ros2xeno({"base_vx": 0.0, "base_wz": 0.0})
    lp.wait_cycles(300)
    assert joints(lp) == pytest.approx(READY, abs=2.5 * DEG)  # held up in RUN
    # STOPPING: lowered at a bounded speed, STOPPED only once at rest on its stops.
    lp.command("stop", "STOPPING")
    fastest, last = 0.0, (time.monotonic(), joints(lp))
    deadline = time.monotonic() + MOVE_S
    while lp.ch.status().state_name == "STOPPING":
        assert time.monotonic() < deadline, f"the arm never reached rest: {joints(lp)}"
        time.sleep(0.1)  # sampling the lowering arm's speed
        now = (time.monotonic(), joints(lp))
        fastest = max(fastest, *(abs(b - a) / (now[0] - last[0]) for a, b in zip(last[1], now[1], strict=True)))
        last = now
    assert lp.ch.status().state_name == "STOPPED"
    assert joints(lp) == pytest.approx(REST, abs=1.0 * DEG)
    assert fastest < CLOSING_MAX, f"lowered at {fastest / DEG:.1f} °/s"
    lp.wait_cycles(300)  # unpowered at rest: it stays there
    assert joints(lp) == pytest.approx(REST, abs=1.0 * DEG)


def test_xrf_echo_sample_has_every_channel_of_the_bench(youbot: LoopProcess, shm_name: str) -> None:
    """`xrf echo sample` (the CLI's io fields) prints the bench's nine channels: an encoder, a PWM
    and a digital output each, two digital inputs each, read through the count in the header."""
    r = subprocess.run(
        [sys.executable, "-m", "xrflab.cli", "echo", "sample", "--count", "1", "--shm", shm_name, "--timeout", "5"],
        capture_output=True,
        text=True,
        timeout=60,
        env=dict(os.environ, PYTHONPATH=str(REPO / "appliance")),
    )
    assert r.returncode == 0, r.stdout + r.stderr
    sample = json.loads(r.stdout.splitlines()[0])
    assert [len(sample[k]) for k in ("enc", "pwm", "dout", "din")] == [9, 9, 9, 18], sample
