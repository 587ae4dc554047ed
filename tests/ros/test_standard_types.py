"""Standard message types in a project's messages (issue 31): ``std_msgs/Header header`` and
fixed-size geometry_msgs, as real XRF2 projects start their Ros2Xeno.msg / Xeno2Ros.msg.

End to end with real parts: the fixture project is built with CMake (its C++ uses
``ros_msg.header.stamp``, ``xeno_msg.pose.position.x``), runs as a loop process, the bridge runs as
its own process, and a separate rclpy node publishes and receives real std_msgs/Header and
geometry_msgs fields (not flattened names).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from xrflab.build import build_project

pytestmark = pytest.mark.ros

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "std_types_controller"

# The course node, in its own process (one project's xrf2_msgs per process).
PEER = r"""
import json, sys, time
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Twist, Vector3
from std_msgs.msg import Header
from xrf2_msgs.msg import Ros2Xeno, Xeno2Ros

rclpy.init()
node = rclpy.create_node("std_types_peer")
qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
got = []
node.create_subscription(Xeno2Ros, "Xeno2Ros", got.append, qos)
pub = node.create_publisher(Ros2Xeno, "Ros2Xeno", qos)
out = {"fields": Ros2Xeno.get_fields_and_field_types(), "xeno2ros_fields": Xeno2Ros.get_fields_and_field_types()}

def publish(frame_id):
    pub.publish(Ros2Xeno(
        header=Header(stamp=Time(sec=12, nanosec=34), frame_id=frame_id),
        cmd=Twist(linear=Vector3(x=1.5, y=-2.0, z=0.5), angular=Vector3(z=0.25)),
        gain=2.0,
    ))

def wait(cond, what, timeout=30.0):
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            out["error"] = "timed out waiting for " + what
            print(json.dumps(out)); sys.exit(1)
        rclpy.spin_once(node, timeout_sec=0.05)

wait(lambda: pub.get_subscription_count() > 0 and got, "the bridge")
def echoed():
    publish("base_link")
    rclpy.spin_once(node, timeout_sec=0.05)
    return got and got[-1].header.frame_id == "base_link"
wait(echoed, "the loop's echo")
m = got[-1]
out["echo"] = {
    "types": [type(m.header).__module__ + "." + type(m.header).__name__,
              type(m.header.stamp).__module__ + "." + type(m.header.stamp).__name__,
              type(m.pose).__module__ + "." + type(m.pose).__name__],
    "stamp": [m.header.stamp.sec, m.header.stamp.nanosec],
    "frame_id": m.header.frame_id,
    "position": [m.pose.position.x, m.pose.position.y],
    "orientation": [m.pose.orientation.z, m.pose.orientation.w],
    "twice_linear": [m.twice_linear.x, m.twice_linear.y, m.twice_linear.z],
    "note": m.note,
}
# A frame name longer than the loop's layout holds: the bridge refuses it (the loop keeps the last).
publish("f" * 40)
n = len(got)
wait(lambda: len(got) >= n + 20, "samples after the long frame_id")
out["after_long"] = got[-1].header.frame_id
print(json.dumps(out))
node.destroy_node()
rclpy.shutdown()
"""


def test_header_and_geometry_types_build_and_round_trip(procs, shm_name, tmp_path, ros_env):
    from xrflab.ros.interfaces import build_interface_package, runtime_env

    exe = build_project(FIXTURE, build_dir=tmp_path / "build", log=lambda line: None).executable
    loop = procs.loop(exe, shm_name)
    # The loop's schema keeps the .msg lines; the host's codec names the leaves by their path.
    assert loop.ch.ros2xeno_codec.schema.splitlines()[0] == "std_msgs/Header header"
    assert "header.stamp.sec" in loop.ch.xeno2ros_codec.field_names
    assert loop.command("initialise").accepted and loop.command("start").accepted
    bridge = procs.bridge(shm_name)  # messages from the running loop's schemas
    env = dict(os.environ, **ros_env, **runtime_env(build_interface_package(FIXTURE / "msg")))
    r = subprocess.run([sys.executable, "-c", PEER], env=env, capture_output=True, text=True, timeout=120)
    lines = [line for line in r.stdout.splitlines() if line.startswith("{")]
    assert r.returncode == 0 and lines, f"peer failed ({r.returncode}):\n{r.stdout}\n{r.stderr}\n{bridge.output}"
    out = json.loads(lines[-1])
    # Real ROS 2 types over DDS: a node's msg.header is a std_msgs/Header.
    assert out["fields"] == {"header": "std_msgs/Header", "cmd": "geometry_msgs/Twist", "gain": "double"}
    assert out["xeno2ros_fields"]["note"] == "string<16>"  # rosidl's name of string<=16
    echo = out["echo"]
    assert echo["types"] == [
        "std_msgs.msg._header.Header",
        "builtin_interfaces.msg._time.Time",
        "geometry_msgs.msg._pose.Pose",
    ]
    assert echo["stamp"] == [12, 35] and echo["frame_id"] == "base_link"  # the loop added 1 ns
    assert echo["position"] == [3.0, -2.0]  # linear.x * gain, linear.y
    assert echo["orientation"] == [0.25, 1.0]  # w: ROS's default 1 survives the loop's layout
    assert echo["twice_linear"] == [3.0, -4.0, 1.0] and echo["note"] == "echo"
    # Too long for the loop's 31 bytes: refused by the bridge with the reason, the loop keeps the last.
    assert out["after_long"] == "base_link"
    assert bridge.terminate() == 0
    assert "Ros2Xeno not written: field header.frame_id" in bridge.output, bridge.output
    assert "holds at most 31" in bridge.output, bridge.output
