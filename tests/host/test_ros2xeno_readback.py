"""Channels.read_ros2xeno: the Ros2Xeno the loop takes, read back by the appliance (the Watch page
and the setpoint controls show it, whoever wrote it: issue 31). Through rt_core's own channels.c."""

from __future__ import annotations

from xrf_testing.testloop import LoopSide, create_for_test
from xrflab.channels import ffi, lib


def test_zero_before_any_write_then_the_latest_whoever_wrote_it(shm_name: str) -> None:
    with create_for_test(shm_name) as ch:
        assert ch.read_ros2xeno() == {"steer_left": 0.0, "steer_right": 0.0}  # the loop's starts at zero
        ch.write_ros2xeno({"steer_left": 1.5})
        assert ch.read_ros2xeno() == {"steer_left": 1.5, "steer_right": 0.0}
        # another writer (the ROS 2 bridge, a CLI) through its own mapping of the same segment
        other = type(ch).open(shm_name, wait_s=1)
        try:
            other.write_ros2xeno({"steer_left": -2.0, "steer_right": 0.25})
        finally:
            other.close()
        assert ch.read_ros2xeno() == {"steer_left": -2.0, "steer_right": 0.25}
        assert LoopSide(ch).read_ros2xeno() == ch.read_ros2xeno()  # what the loop itself reads


def test_a_write_in_progress_reads_as_none_not_as_a_torn_message(shm_name: str) -> None:
    with create_for_test(shm_name) as ch:
        ch.write_ros2xeno({"steer_left": 3.0})
        seq = ffi.addressof(ch.shm.ros2xeno, "seq")
        held = lib.xrfpy_load_u32(seq)
        lib.xrfpy_store_u32(seq, held + 1)  # odd: a writer is in the middle of one
        try:
            assert ch.read_ros2xeno() is None
        finally:
            lib.xrfpy_store_u32(seq, held)
        assert ch.read_ros2xeno() == {"steer_left": 3.0, "steer_right": 0.0}


def test_the_appliance_merges_a_setpoint_into_what_the_loop_has(shm_name: str) -> None:
    """A field written by another writer (the ROS 2 bridge maps the segment itself) is kept when
    the dashboard changes another one: it was put back to the appliance's last value."""
    from types import SimpleNamespace

    from xrflab.server.runs import control

    with create_for_test(shm_name) as ch:
        run = SimpleNamespace(channels=ch, setpoint={})
        assert control.setpoint(run, {"steer_left": 1.0}) == {"steer_left": 1.0, "steer_right": 0.0}
        ch.write_ros2xeno({"steer_left": 1.0, "steer_right": 4.0})  # the bridge, behind our back
        merged = control.setpoint(run, {"steer_left": 2.0})
        assert merged == {"steer_left": 2.0, "steer_right": 4.0}
        assert ch.read_ros2xeno() == merged and run.setpoint == merged
