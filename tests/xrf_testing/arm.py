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

import pytest

from xrflab import plants
from xrflab.build import build_project
from xrflab.channels import Channels
from xrflab.server.runs.safety import SafetyWatcher

from .harness import Server
from .loops import LoopProcess

FAULTS = ("segfault", "hang", "exit0", "stopping_never_returns")
# FAULTS as pytest parameters: the hang (a busy loop at real-time priority on the loop's CPU) is
# an `rt_hog`, run after the parallel part of the suite, alone (tests/xrf_testing/tiers.py).
FAULT_PARAMS = [pytest.param(f, marks=pytest.mark.rt_hog) if f == "hang" else f for f in FAULTS]
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
    """The joint angles a simulated board mirrors: a run's (its Channels) or a test's own board's
    (a ``struct xrf_sim_outputs``: the watcher's real-bench path, tests/rt_core/test_hold_board.py)."""
    sim = ch.shm.sim if hasattr(ch, "shm") else ch
    return [float(sim.plant[i]) for i in range(5)]


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
        if r is not None and (r.rest_ns or r.hold_status):  # at rest, or the hold given up
            return worst, {"result": r, "pose": q}
        assert time.monotonic() < deadline, (
            f"the arm never came to rest: {'still watching' if r is None else r.describe()}"
            f" (reason {None if r is None else r.reason}, hold_status {None if r is None else r.hold_status},"
            f" phase {None if r is None else r.hold_phase}); pose {q}"
        )
        time.sleep(0.002)  # sampling the arm's motion: finer than its 20 °/s could hide a drop


def assert_held_to_rest(label: str, worst: float, r, end: dict) -> None:  # noqa: ANN001
    """A fault's `hold` as every fault test checks it: the first safe output within 100 ms, the
    largest excursion `worst` (rad, the test's own sampling of the arm) and the watcher's own drop
    under DROP_BOUND, and the arm on its rest stops at the end (end["pose"], follow's). Prints the
    figures (the safety bench quotes them)."""
    assert r.safe_ns - r.event_ns < 100_000_000
    rest_s = (r.rest_ns - r.event_ns) / 1e9
    print(
        f"{label}: largest drop {math.degrees(worst):.2f}° (watcher: {math.degrees(r.drop_urad / 1e6):.2f}°), "
        f"at rest {rest_s:.2f} s after the fault"
    )
    assert worst < DROP_BOUND, f"{label}: a joint dropped {math.degrees(worst):.2f}°"
    assert r.drop_urad < DROP_BOUND * 1e6
    for j, rest in REST.items():
        assert abs(end["pose"][j] - rest) < math.radians(1.0), (j, end["pose"])


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


# ---- the whole appliance killed (tests/server/test_appliance_kill_hold.py, bench/safety/arm.py) ----

# The youBot example's ready pose (student_projects/examples/youbot): J2..J4, where INITIALISING
# raises the arm and RUN holds it.
EXAMPLE_READY = {1: math.radians(10.0), 2: math.radians(60.0), 3: math.radians(40.0)}


def ended(pid: int) -> bool:
    """The process has ended (gone, or a zombie nobody reaped: its parent was the appliance)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except (OSError, IndexError):
        return True


def comm(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/comm").read_text().strip()
    except OSError:
        return ""


def raise_example(server: Server) -> tuple[dict, Channels]:
    """A youBot example run on `server`, in RUN with the arm at its ready pose; its segment mapped
    by us (the plant stays observable once the appliance is gone: nothing else names the memfd)."""
    run = server.start_run("youbot")
    assert run["sim"] == "youbot", run
    ch = Channels.open(run["shm"], wait_s=5)
    with server.ws() as ws:
        assert ws.command("initialise")["accepted"]
        ws.wait_state("INITIALISED", 30)  # the example raises the arm to its ready pose first
        assert ws.command("start")["accepted"]
        ws.wait_state("RUN", 10)
    q = pose(ch)
    for j, up in EXAMPLE_READY.items():
        assert abs(q[j] - up) < math.radians(3.0), ("the arm is not up", q)
    return run, ch


def follow_until_ended(ch: Channels, held: list[float], t_fault: float, pid: int, timeout: float = 30) -> float:
    """Sample the arm until process `pid` (the run's xrf-watch) has ended: the largest excursion
    (rad) outside what `hold` may do (the pose at the fault for HOLD_S, then the span from there
    to the rest pose)."""
    worst, deadline = 0.0, t_fault + timeout
    while not ended(pid):
        q, t = pose(ch), time.monotonic() - t_fault
        for j, rest in REST.items():
            if t < HOLD_S:
                worst = max(worst, abs(q[j] - held[j]))
            lo, hi = min(rest, held[j]), max(rest, held[j])
            worst = max(worst, lo - q[j], q[j] - hi)
        assert time.monotonic() < deadline, f"xrf-watch never finished; pose {q}"
        time.sleep(0.002)  # sampling the lowering arm: finer than 20 °/s could hide a drop
    return worst
