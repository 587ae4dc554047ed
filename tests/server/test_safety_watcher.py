"""The safety watcher (rt_core/src/watch.c through server/runs/safety.py) on real processes.

The shared memory here is a real `struct xrf_shm` in this process's memory (what the watcher
reads and writes is the same layout the loop maps): the point is what the watcher does to a
process and to that memory, and that it does it while this Python process is busy."""

from __future__ import annotations

import errno
import math
import os
import re
import signal
import subprocess
import time

import pytest

from xrflab.channels import ffi, lib
from xrflab.server.runs.safety import SafetyWatcher


class _FakeChannels:
    """Just the `shm` attribute SafetyWatcher uses, over a zeroed `struct xrf_shm`."""

    def __init__(self) -> None:
        self.shm = ffi.new("struct xrf_shm *")


@pytest.fixture
def child():
    proc = subprocess.Popen(["sleep", "60"])
    yield proc
    if proc.poll() is None:
        proc.kill()
    proc.wait()


def _wait_result(w: SafetyWatcher, timeout: float = 5.0):
    deadline = time.monotonic() + timeout
    while (r := w.result()) is None:
        assert time.monotonic() < deadline, "the watcher did not act"
        time.sleep(0.001)  # the watcher's reaction time is what is asserted: poll finer than wait_for
    return r


def test_exit_forces_the_simulated_outputs_off_and_then_notifies(child) -> None:
    ch = _FakeChannels()
    ch.shm.sim.active = 1
    ch.shm.sim.pwm[0] = 400
    ch.shm.sim.dout[1] = 1
    w = SafetyWatcher(child.pid, ch, hang_timeout_ms=200, check_ms=20, force_sim=True)  # type: ignore[arg-type]
    try:
        assert w.result() is None
        t_kill = time.monotonic_ns()
        child.kill()
        r = _wait_result(w)
        assert r.reason == "exit" and r.sim_forced
        assert ch.shm.sim.forced_off == 1 and ch.shm.sim.pwm[0] == 0 and ch.shm.sim.dout[1] == 0
        assert t_kill <= r.event_ns <= r.safe_ns
        assert r.safe_ns - t_kill < 100_000_000, f"safe {(r.safe_ns - t_kill) / 1e6:.1f} ms after the kill"
        assert r.reset_status == lib.XRF_WATCH_RESET_NOT_TRIED  # no spidev was configured
        # The eventfd turned readable only once the outputs were safe.
        assert os.read(w.fileno(), 8) == (1).to_bytes(8, "little")
        assert r.describe() == "sim outputs forced off"
    finally:
        assert w.stop().reason == "exit"


def test_the_watcher_acts_while_this_process_holds_the_gil(child) -> None:
    """Nothing in the appliance's Python (the event loop, a GC pause, a long C call holding the
    GIL) sits between the exit and the safe outputs."""
    ch = _FakeChannels()
    w = SafetyWatcher(child.pid, ch, hang_timeout_ms=200, check_ms=20, force_sim=True)  # type: ignore[arg-type]
    try:
        killer = subprocess.Popen(["sh", "-c", f"sleep 0.3; kill -9 {child.pid}"])
        t0 = time.monotonic_ns()
        # The regular-expression engine holds the GIL for the whole match (about a second here).
        assert re.match(r"(a+)+$", "a" * 25 + "b") is None
        gil_released = time.monotonic_ns()
        killer.wait()
        r = _wait_result(w)
        assert gil_released - t0 > 400_000_000, "the GIL was not held long enough to prove anything"
        assert r.reason == "exit"
        assert t0 < r.safe_ns < gil_released, "outputs were made safe only after Python let go"
        assert r.safe_ns - r.event_ns < 100_000_000
    finally:
        w.stop()


def test_a_hung_loop_is_killed_after_the_outputs_are_safe(child) -> None:
    ch = _FakeChannels()
    status = ch.shm.status
    status.running = 1
    status.heartbeat_ns = time.monotonic_ns()  # one beat, then none: hung
    w = SafetyWatcher(child.pid, ch, hang_timeout_ms=150, check_ms=10, force_sim=True)  # type: ignore[arg-type]
    try:
        r = _wait_result(w)
        assert r.reason == "hang" and r.kill_status == 0 and r.sim_forced
        assert r.heartbeat_ns == status.heartbeat_ns
        assert 150_000_000 <= r.event_ns - r.heartbeat_ns < 150_000_000 + 100_000_000
        assert child.wait(timeout=5) == -signal.SIGKILL
    finally:
        w.stop()


def test_a_beating_loop_is_left_alone_and_stop_cancels(child) -> None:
    ch = _FakeChannels()
    ch.shm.status.running = 1
    w = SafetyWatcher(child.pid, ch, hang_timeout_ms=100, check_ms=10, force_sim=True)  # type: ignore[arg-type]
    try:
        end = time.monotonic() + 0.5
        while time.monotonic() < end:  # the loop's heartbeat, every 5 ms
            ch.shm.status.heartbeat_ns = time.monotonic_ns()
            time.sleep(0.005)
        assert w.result() is None and child.poll() is None
    finally:
        r = w.stop()
    assert r.reason == "cancelled" and not r.sim_forced and ch.shm.sim.forced_off == 0


def test_stop_after_the_exit_still_makes_the_outputs_safe(child) -> None:
    """The appliance may learn of the exit (its launcher ended) before the watcher ran: stopping
    the watcher then must not skip the safe state."""
    ch = _FakeChannels()
    w = SafetyWatcher(child.pid, ch, hang_timeout_ms=0, check_ms=1000, force_sim=True)  # type: ignore[arg-type]
    child.kill()
    child.wait()
    r = w.stop()
    assert r.reason == "exit" and ch.shm.sim.forced_off == 1


def test_a_reset_device_that_fails_is_reported(child) -> None:
    w = SafetyWatcher(child.pid, None, hang_timeout_ms=0, check_ms=50, force_sim=False, spi_device="/dev/null")
    child.kill()
    r = _wait_result(w)
    w.stop()
    assert r.reason == "exit" and not r.sim_forced
    assert r.describe() == "FPGA RESET failed: Inappropriate ioctl for device"


def test_a_process_already_gone_is_refused_at_start() -> None:
    proc = subprocess.Popen(["true"])
    proc.wait()
    with pytest.raises(ProcessLookupError):
        SafetyWatcher(proc.pid, None, hang_timeout_ms=0, check_ms=50, force_sim=False)


def test_the_brake_reaction_leaves_the_brake_output_on_and_every_pwm_zero(child) -> None:
    """safe reaction `brake` (watch.h's XRF_SAFE_REACTIONS): PWM zero like `zero`, but the brake's
    digital output is forced on (forced_dout, which the simulated board's pins show from then on)
    and every other output off, within the same bound."""
    ch = _FakeChannels()
    ch.shm.sim.active = 1
    ch.shm.sim.pwm[1] = -300
    ch.shm.sim.dout[0] = 1  # a student's output on channel 1: must go off
    ch.shm.sim.forced_dout[3] = 1  # the loop can write this too: the watcher rewrites all of it
    w = SafetyWatcher(
        child.pid,
        ch,  # type: ignore[arg-type]
        hang_timeout_ms=200,
        check_ms=20,
        force_sim=True,
        safe_reaction="brake",
        brake_channel=3,
    )
    try:
        t_kill = time.monotonic_ns()
        child.kill()
        r = _wait_result(w)
        assert r.reason == "exit" and r.sim_forced and r.brake_channel == 3
        sim = ch.shm.sim
        assert sim.forced_off == 1
        assert list(sim.forced_dout) == [0, 0, 1, 0] and list(sim.dout) == [0, 0, 1, 0]
        assert list(sim.pwm) == [0, 0, 0, 0]
        assert r.safe_ns - t_kill < 100_000_000, f"safe {(r.safe_ns - t_kill) / 1e6:.1f} ms after the kill"
        assert r.describe() == "sim outputs forced off but the brake on channel 3"
    finally:
        w.stop()


def test_the_zero_reaction_forces_every_digital_output_off(child) -> None:
    ch = _FakeChannels()
    ch.shm.sim.forced_dout[1] = 1  # left there by the loop: zero means zero
    w = SafetyWatcher(child.pid, ch, hang_timeout_ms=0, check_ms=50, force_sim=True)  # type: ignore[arg-type]
    child.kill()
    r = _wait_result(w)
    w.stop()
    assert r.brake_channel == 0 and list(ch.shm.sim.forced_dout) == [0, 0, 0, 0]


def test_a_brake_frame_is_sent_over_spidev_as_an_all_frame(child) -> None:
    """On a real bench `brake` sends an ALL frame (not RESET, which would switch the brake's
    output off); a device that cannot take it is reported like a failed RESET."""
    w = SafetyWatcher(
        child.pid,
        None,
        hang_timeout_ms=0,
        check_ms=50,
        force_sim=False,
        spi_device="/dev/null",
        safe_reaction="brake",
        brake_channel=2,
    )
    child.kill()
    r = _wait_result(w)
    w.stop()
    assert r.reset_status == -errno.ENOTTY
    assert lib.xrf_fpga_brake(b"/dev/null", 1_000_000, 5) == -errno.EINVAL


@pytest.mark.parametrize(
    ("reaction", "brake_channel", "message"),
    [
        ("drop", 0, "unknown safe reaction 'drop'"),
        ("brake", 0, "needs a brake channel 1..4"),
        ("brake", 5, "needs a brake channel"),
    ],
)
def test_a_reaction_the_watcher_cannot_carry_out_is_refused_at_start(child, reaction, brake_channel, message) -> None:
    with pytest.raises(ValueError, match=message):
        SafetyWatcher(
            child.pid,
            None,
            hang_timeout_ms=0,
            check_ms=50,
            force_sim=False,
            safe_reaction=reaction,
            brake_channel=brake_channel,
        )


def test_the_reactions_are_named_from_the_c_list() -> None:
    from xrflab.channels import SAFE_REACTIONS

    assert SAFE_REACTIONS == {
        "zero": lib.XRF_SAFE_REACTION_ZERO,
        "brake": lib.XRF_SAFE_REACTION_BRAKE,
        "hold": lib.XRF_SAFE_REACTION_HOLD,
    }
    for name, number in SAFE_REACTIONS.items():
        assert ffi.string(lib.xrf_safe_reaction_name(number)).decode() == name
        assert lib.xrf_safe_reaction_parse(name.encode()) == number
    assert lib.xrf_safe_reaction_name(lib.XRF_SAFE_REACTION_COUNT) == ffi.NULL
    assert lib.xrf_safe_reaction_parse(b"Zero") == -errno.EINVAL


def test_the_runs_plant_profile_names_the_reaction(tmp_path, monkeypatch, caplog) -> None:
    """server/runs/watch.py passes the bench profile's reaction to the watcher: the run's plant's
    profile (an educator's edited copy first) on the simulated bench, XRF_BENCH_PROFILE's on a real
    one; none, or one that does not load, is `zero` (said in the log)."""
    from xrflab import profiles as prof
    from xrflab.server.runs.watch import run_safe_reaction
    from xrflab.server.settings import Settings

    settings = Settings(data_dir=tmp_path)
    assert run_safe_reaction("stage", False, settings) == prof.SafeReaction("zero", 0, 0)
    edited = prof.load_profile("stage")
    edited["safety"] = {"reaction": "brake", "brake_channel": 2}
    prof.save_profile(edited, tmp_path)
    assert run_safe_reaction("stage", False, settings) == prof.SafeReaction("brake", 1, 2)
    monkeypatch.delenv("XRF_BENCH_PROFILE", raising=False)
    assert run_safe_reaction("stage", True, settings).name == "zero"  # a real bench names its own
    monkeypatch.setenv("XRF_BENCH_PROFILE", "stage")
    assert run_safe_reaction("relbot", True, settings).name == "brake"
    (prof.profiles_dir(tmp_path) / "stage.json").write_text('{"name": "stage", "safety": {"reaction": "hover"}}')
    assert run_safe_reaction("stage", False, settings).name == "zero"
    assert "unusable" in caplog.text and "hover" in caplog.text


def test_hold_needs_a_plant_with_an_arm(child) -> None:
    """`hold` on the simulated board steps the run's plant: one without an arm model is refused
    at start (RELbot), never found out when the outputs must be made safe."""
    from xrflab import plants

    ch = _FakeChannels()
    for plant in (0, plants.get("relbot").id, 999):
        with pytest.raises(ValueError, match="needs a simulated plant with an arm model"):
            SafetyWatcher(
                child.pid, ch, hang_timeout_ms=0, check_ms=20, force_sim=True, safe_reaction="hold", plant=plant
            )  # type: ignore[arg-type]


@pytest.mark.parametrize("poison", ["nan", "huge", "odd_seq"])
def test_hold_takes_a_hostile_snapshot_and_still_puts_the_arm_down(child, poison) -> None:
    """The snapshot the watcher steps the arm on from is in memory the loop (the student's
    program) writes: NaN, absurd values, a seqlock left odd for ever. The watcher neither crashes
    nor hangs on it; the arm it simulates ends at its rest pose within the law's bound."""
    from xrflab import plants

    ch = _FakeChannels()
    snap = ch.shm.sim_snapshot
    values = {"nan": float("nan"), "huge": 1e308, "odd_seq": 0.0}[poison]
    for i in range(lib.XRF_SIM_SNAPSHOT_MAX):
        snap.v[i] = -values if i % 2 else values
    snap.seq = 7 if poison == "odd_seq" else 2
    snap.n = 0xFFFFFFFF
    w = SafetyWatcher(
        child.pid,
        ch,
        hang_timeout_ms=0,
        check_ms=20,
        force_sim=True,
        safe_reaction="hold",
        plant=plants.get("youbot").id,
    )  # type: ignore[arg-type]
    child.kill()
    _wait_result(w)  # the exit seen (a stop() before it would cancel the watch)
    r = w.stop()  # waits for the closing sequence: bounded by the law's max_s (20 s)
    assert r.reason == "exit" and r.hold_phase == 3 and r.rest_ns >= r.safe_ns > 0
    assert r.safe_ns - r.event_ns < 100_000_000
    pose = [ch.shm.sim.plant[i] for i in range(8)]
    assert all(math.isfinite(v) for v in pose), pose
    rest = [math.radians(d) for d in (-65.0, 151.0, -102.5)]
    assert all(abs(q - want) < math.radians(1.0) for q, want in zip(pose[1:4], rest, strict=True)), pose
    assert list(ch.shm.sim.pwm) == [0, 0, 0, 0]
