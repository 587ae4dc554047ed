"""The safety watcher (rt_core/src/watch.c through server/runs/safety.py) on real processes.

The shared memory here is a real `struct xrf_shm` in this process's memory (what the watcher
reads and writes is the same layout the loop maps): the point is what the watcher does to a
process and to that memory, and that it does it while this Python process is busy."""

from __future__ import annotations

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
