"""The bridge's message mapping and its no-drop reading, against a Python-driven loop side
(``xrf_testing.testloop.create_for_test``: the real shared memory and ring code, no loop process) and real
rclpy in this process."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from xrf_testing.testloop import LoopSide, create_for_test
from xrflab.channels import shm_path

pytestmark = pytest.mark.ros

ROS2XENO = "float64 speed\nint32 mode\nbool enable\nfloat32[3] gains\nuint8 flags\nint64 t_sent_ns"
XENO2ROS = "int64 seq\nfloat64[2] pos\nbool ok\nint16 pwm\nuint32 count"


@pytest.fixture
def loop_side(shm_name: str, tmp_path: Path):
    ch = create_for_test(shm_name, ros2xeno_schema=ROS2XENO, xeno2ros_schema=XENO2ROS)
    yield ch, LoopSide(ch)
    ch.close()
    try:
        shm_path(shm_name).unlink()
    except FileNotFoundError:
        pass


def _spin_until(ex, cond, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        ex.spin_once(timeout_sec=0.01)


def test_types_both_ways_and_a_burst_of_900_samples_arrives_complete(loop_side, ros_env, tmp_path):
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Int32

    from xrflab.ros.bridge import Bridge, msg_dir_from_loop, prepare_messages

    ch, side = loop_side
    # The msg/ folder written from the loop's schemas is what `xrf ros-bridge` uses by default.
    msg_dir = msg_dir_from_loop(ch, tmp_path / "msg")
    assert (msg_dir / "Xeno2Ros.msg").read_text() == XENO2ROS + "\n"
    ros2xeno, xeno2ros = prepare_messages(ch, None, log=lambda s: None)
    side.set_state(1)

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        bridge = Bridge(ch, ros2xeno, xeno2ros, user="u", context=ctx, state_period=0.2)
        peer = rclpy.create_node("types_peer", context=ctx)
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        got: list = []
        states: list[int] = []
        peer.create_subscription(xeno2ros, "Xeno2Ros", got.append, qos)
        peer.create_subscription(Int32, "XenoState", lambda m: states.append(m.data), qos)
        pub = peer.create_publisher(ros2xeno, "Ros2Xeno", qos)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(bridge.node)
        ex.add_node(peer)
        bridge.start()
        _spin_until(ex, lambda: pub.get_subscription_count() > 0 and states, 10, "discovery")

        # ROS -> loop: every field type, mapped by name through the loop's codec.
        pub.publish(ros2xeno(speed=1.25, mode=-7, enable=True, gains=[0.5, 1.5, 2.5], flags=200, t_sent_ns=123))
        seen: list = []
        _spin_until(ex, lambda: seen.append(side.read_ros2xeno()) or seen[-1] is not None, 5, "Ros2Xeno in shm")
        assert seen[-1] == {
            "speed": 1.25,
            "mode": -7,
            "enable": True,
            "gains": [0.5, 1.5, 2.5],
            "flags": 200,
            "t_sent_ns": 123,
        }

        # loop -> ROS: a burst of 900 samples in one go (the ring holds 1024), one doorbell.
        for i in range(900):
            side.publish_telemetry(
                1000 + i,
                xeno2ros={"seq": i, "pos": [i * 0.5, -i * 0.25], "ok": i % 2 == 0, "pwm": -i, "count": 7 * i},
                ring=False,
            )
        side.ring_doorbell()
        _spin_until(ex, lambda: len(got) >= 900, 20, "900 Xeno2Ros")
        assert [m.seq for m in got] == list(range(900))
        m = got[301]
        assert list(m.pos) == [150.5, -75.25] and m.ok is False and m.pwm == -301 and m.count == 2107

        # State changes are published at once, and periodically.
        side.set_state(4)
        side.ring_doorbell()
        _spin_until(ex, lambda: states[-1] == 4, 5, "XenoState 4")
        n = len(states)
        _spin_until(ex, lambda: len(states) >= n + 2, 5, "periodic XenoState")
        assert bridge.lost == 0 and bridge.published == 900
        assert bridge.stop(5.0)
        ex.shutdown(timeout_sec=1)
    finally:
        rclpy.try_shutdown(context=ctx)


def test_command_gate_is_asked_and_can_refuse(loop_side, ros_env):
    """The gate sees (user, cmd) for every XenoCmd and can refuse; what it lets through goes
    to the command ring with source ROS and the loop's verdict (the C command table, applied by
    LoopSide) is logged."""
    import threading

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from std_msgs.msg import Int32

    from xrflab.channels import lib
    from xrflab.ros.bridge import Bridge, prepare_messages

    ch, side = loop_side
    ros2xeno, xeno2ros = prepare_messages(ch, None, log=lambda s: None)
    side.set_state(1)
    asked: list[tuple[str, int]] = []
    taken: list[tuple[int, int]] = []
    stop = threading.Event()

    def loop() -> None:  # the loop's command handling, one command per "cycle"
        while not stop.is_set():
            got = side.poll_command()
            if got is not None:
                ticket, cmd, source = got
                taken.append((cmd, source))
                side._apply(ticket, cmd)
                side.ring_doorbell()
            time.sleep(0.001)

    def gate(user: str, cmd: int):
        asked.append((user, cmd))
        return (cmd != 1, "bench is leased to bob")

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    worker = threading.Thread(target=loop, daemon=True)
    worker.start()
    try:
        bridge = Bridge(ch, ros2xeno, xeno2ros, user="alice", command_gate=gate, context=ctx)
        peer = rclpy.create_node("gate_peer", context=ctx)
        pub = peer.create_publisher(Int32, "XenoCmd", 10)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(bridge.node)
        ex.add_node(peer)
        bridge.start()
        _spin_until(ex, lambda: pub.get_subscription_count() > 0, 10, "discovery")
        for cmd in (1, 2):  # initialise: refused by the gate; start: rejected by the loop (IDLE)
            pub.publish(Int32(data=cmd))
        _spin_until(ex, lambda: len(asked) == 2 and len(taken) == 1, 5, "both commands handled")
        assert asked == [("alice", 1), ("alice", 2)]
        assert taken == [(2, lib.XRF_SOURCE_ROS)]
        _spin_until(ex, lambda: ch.status().rejected_count == 1, 5, "the rejection")
        status = ch.status()
        assert status.state_name == "IDLE" and status.last_rejected_cmd == 2 and status.reject_reason
        assert bridge.commands_sent == 1
        assert bridge.stop(5.0)
        ex.shutdown(timeout_sec=1)
    finally:
        stop.set()
        rclpy.try_shutdown(context=ctx)


def test_fields_that_do_not_match_are_refused(loop_side, ros_env):
    from std_msgs.msg import Int32

    from xrflab.ros.bridge import MessageMap

    ch, _side = loop_side
    with pytest.raises(RuntimeError, match="differ from the loop's"):
        MessageMap(ch.xeno2ros_codec, Int32)
