"""The youBot arm raised by a real loop process and a fault that takes its controller away: what
tests/rt_core/test_hold_faults.py asserts and bench/safety/arm.py measures (docs/developers/safety.md).
The loop is tests/fixtures/arm_faults on the simulated youBot; the safety watcher is rt_core's, as
server/runs/safety.py starts it; every figure is read from the plant state the watcher mirrors."""

from __future__ import annotations

import math
import os
import signal
import time
from pathlib import Path

from xrflab import plants
from xrflab.build import build_project
from xrflab.server.runs.safety import SafetyWatcher

from .loops import LoopProcess

FAULTS = ("segfault", "hang", "exit0", "stopping_never_returns")
REPO = Path(__file__).resolve().parents[2]
ARM_FAULTS = REPO / "tests/fixtures/arm_faults"
DROP_BOUND = math.radians(2.0)
# The plant's rest pose (plant_youbot.c): J2 back on its stop, J3 forward on its, J4 back on its.
REST = {1: math.radians(-65.0), 2: math.radians(151.0), 3: math.radians(-102.5)}
# The fixture's working pose (tests/fixtures/arm_faults/src/main.cpp).
WORK = [math.radians(d) for d in (10.0, -20.0, 100.0, -60.0)]
HOLD_S = 0.5  # the law's hold phase before it lowers (plant_youbot.c's arm)


def raise_arm(lp: LoopProcess) -> None:
    lp.command("initialise", "INITIALISED")
    lp.command("start", "RUN")
    deadline = time.monotonic() + 15
    while any(abs(q - w) > math.radians(2.0) for q, w in zip(pose(lp.ch)[1:4], WORK[1:4], strict=True)):
        assert time.monotonic() < deadline, f"the arm never reached its working pose: {pose(lp.ch)}"
        time.sleep(0.02)  # polling the plant; the arm moves at 20 °/s


def pose(ch) -> list[float]:
    return [float(ch.shm.sim.plant[i]) for i in range(5)]


def follow(w: SafetyWatcher, ch, held: list[float], t_fault: float) -> tuple[float, dict]:
    """Sample the mirrored pose until the watcher says the arm is at rest; the largest excursion
    (rad) outside what the reaction may do (see the module's doc)."""
    worst = 0.0
    deadline = time.monotonic() + 30
    while True:
        r = w.result()
        q = pose(ch)
        t = time.monotonic() - t_fault
        for j, rest in REST.items():
            if t < HOLD_S:
                worst = max(worst, abs(q[j] - held[j]))
            lo, hi = min(rest, held[j]), max(rest, held[j])
            worst = max(worst, lo - q[j], q[j] - hi)
        if r is not None and r.rest_ns:
            return worst, {"result": r, "pose": q}
        assert time.monotonic() < deadline, "the arm never came to rest"
        time.sleep(0.002)  # sampling the arm's motion: finer than its 20 °/s could hide a drop


def watch(lp: LoopProcess) -> SafetyWatcher:
    return SafetyWatcher(
        lp.proc.pid,
        lp.ch,
        hang_timeout_ms=60,
        check_ms=5,
        force_sim=True,
        safe_reaction="hold",
        plant=plants.get("youbot").id,
    )


def inject(lp: LoopProcess, fault: str) -> float:
    """Inject `fault`; the monotonic time it took effect."""
    if fault == "stopping_never_returns":
        lp.ch.write_ros2xeno({"stop_hang": True})
        lp.command("stop", "STOPPING")
        # The appliance's stop gives STOPPING its time, then terminate(): SIGINT first (the
        # runtime's safe stop), as server/runs/control.py does.
        time.sleep(0.3)  # the time STOPPING is given before the host gives up on it
        assert lp.ch.status().state_name == "STOPPING"
        t = time.monotonic()
        os.kill(lp.proc.pid, signal.SIGINT)
        return t
    t = time.monotonic()
    lp.ch.write_ros2xeno({{"segfault": "crash", "hang": "hang", "exit0": "exit0"}[fault]: True})
    return t


def build_arm(out: Path) -> Path:
    return build_project(ARM_FAULTS, build_dir=out, log=lambda line: None).executable
