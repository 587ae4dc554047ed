"""The ROS 2 bridge end to end: loop process <-> bridge process <-> a separate ROS 2 node process.

Real rclpy and Fast DDS on loopback (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, a random
ROS_DOMAIN_ID per run); the loops are real controller processes on the simulated board.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
RELBOT = REPO / "student_projects/examples/relbot"
PROBE = REPO / "bench/ros/probe_project"

pytestmark = pytest.mark.ros


def _result(rc: int, out: str) -> dict:
    lines = [line for line in out.splitlines() if line.startswith("{")]
    assert lines, f"the peer node printed no result (exit {rc}):\n{out}"
    result = json.loads(lines[-1])
    assert rc == 0 and result["ok"], f"peer failed: {result}\n{out}"
    return result


# ---- the interface package ----------------------------------------------------------------------


def test_interface_package_is_a_real_ros2_package(ros_env, tmp_path):
    from xrflab.ros.interfaces import build_interface_package, runtime_env

    prefix = build_interface_package(RELBOT / "msg")
    share = prefix / "share" / "xrf2_msgs"
    xml = (share / "package.xml").read_text()
    assert '<package format="3">' in xml and "<member_of_group>rosidl_interface_packages</member_of_group>" in xml
    # The cache is keyed by the messages' fields, not their comments: whichever build came first
    # (a project's files, or a running loop's schema) wrote the package, with the same fields.
    from xrflab.msgdef import parse_msg_file, schema_text

    for name in ("Ros2Xeno", "Xeno2Ros"):
        built, ours = share / "msg" / f"{name}.msg", RELBOT / "msg" / f"{name}.msg"
        assert schema_text(parse_msg_file(built)) == schema_text(parse_msg_file(ours)), name
    assert (prefix / "include" / "xrf2_msgs" / "xrf2_msgs" / "msg" / "ros2_xeno.hpp").is_file()  # for C++ nodes
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / "xrf2_msgs").is_file()
    t0 = time.monotonic()
    assert build_interface_package(RELBOT / "msg") == prefix  # cached by message contents
    assert time.monotonic() - t0 < 1.0
    # A fresh interpreter with only the returned variables imports the types as an XRF2 node does.
    code = (
        "from xrf2_msgs.msg import Ros2Xeno, Xeno2Ros; import rclpy; rclpy.init(); "
        "n = rclpy.create_node('t'); n.create_publisher(Ros2Xeno, 'Ros2Xeno', 10).publish(Ros2Xeno(steer_left=1.5)); "
        "print(Ros2Xeno.get_fields_and_field_types(), Xeno2Ros.get_fields_and_field_types())"
    )
    import os

    r = subprocess.run(
        [sys.executable, "-c", code],
        env=dict(os.environ, **ros_env, **runtime_env(prefix)),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    assert "{'steer_left': 'double', 'steer_right': 'double'} {'pos_left': 'double', 'pos_right': 'double'}" in r.stdout


def test_different_messages_get_their_own_prefix(tmp_path):
    from xrflab.ros.interfaces import messages_hash

    other = tmp_path / "msg"
    other.mkdir()
    (other / "Ros2Xeno.msg").write_text("float64 steer_left\nfloat64 steer_right")  # no comments, no newline
    (other / "Xeno2Ros.msg").write_text("float64 pos_left\nfloat64 pos_right\n")
    assert messages_hash(other) == messages_hash(RELBOT / "msg")  # same fields, same package
    (other / "Xeno2Ros.msg").write_text("float64 pos_left\nfloat32 pos_right\n")
    assert messages_hash(other) != messages_hash(RELBOT / "msg")


# ---- RELbot: commands, state, setpoints ---------------------------------------------------------


def test_relbot_commands_state_and_tracking(procs, relbot_exe, shm_name):
    loop = procs.loop(relbot_exe, shm_name)
    bridge = procs.bridge(shm_name, "--user", "alice", "--msg-dir", str(RELBOT / "msg"))
    rc, out = procs.peer(RELBOT / "msg", "relbot", "--left", "1.0", "--right", "-0.5", "--tol", "0.05", timeout=90)
    result = _result(rc, out)
    states = result["states"]
    assert states[0] == 1, states  # IDLE before anything was sent
    assert states.index(3) < states.index(4), states  # INITIALISED, then RUN
    assert loop.ch.status().state_name == "RUN"
    # Xeno2Ros started at the origin and followed the setpoints.
    assert abs(result["first"][0]) < 0.5 and abs(result["first"][1]) < 0.5, result
    assert result["settled"], result
    assert abs(result["final"][0] - 1.0) < 0.05 and abs(result["final"][1] + 0.5) < 0.05, result
    assert bridge.terminate() == 0  # SIGTERM: orderly shutdown, exit 0
    log = bridge.output
    assert "XenoCmd 1 (initialise) accepted" in log and "XenoCmd 2 (start) accepted: state RUN" in log, log
    assert "for user 'alice'" in log
    assert ", 0 lost in the ring" in log, log


def test_first_release_topic_names_command_and_xenomai_state(procs, relbot_exe, shm_name):
    """A node written for the first XRF2 release commands on `Command` and listens on
    `Xenomai_state`: the same bridge answers it (and a v1.1 node at the same time)."""
    loop = procs.loop(relbot_exe, shm_name)
    bridge = procs.bridge(shm_name, "--msg-dir", str(RELBOT / "msg"))
    rc, out = procs.peer(
        RELBOT / "msg", "relbot", "--release", "v1.0", "--left", "0.5", "--right", "0.5", "--tol", "0.05", timeout=90
    )
    result = _result(rc, out)
    states = result["states"]
    assert states[0] == 1 and states.index(3) < states.index(4), states
    assert loop.ch.status().state_name == "RUN"
    assert result["settled"], result
    assert bridge.terminate() == 0
    assert "XenoCmd 2 (start) accepted: state RUN" in bridge.output, bridge.output


# ---- no loss over a soak ------------------------------------------------------------------------

# 15 s in the suite; the 60 s soak is bench/ros/soak.sh (the same test, XRF_ROS_SOAK_SECONDS=60).
SOAK_SECONDS = int(os.environ.get("XRF_ROS_SOAK_SECONDS", "15"))


def test_no_xeno2ros_lost_over_a_soak(procs, probe_exe, shm_name):
    """1 kHz loop, Xeno2Ros decimated to 100 Hz: a separate node receives every sample; the
    cycle numbers they carry advance by exactly 10, with no gap, for the whole soak."""
    loop = procs.loop(probe_exe, shm_name)
    assert loop.ch.info["cycle_freq"] == 1000 and loop.ch.info["write_decimator_freq"] == 100
    assert loop.command("initialise").accepted and loop.command("start").accepted
    bridge = procs.bridge(shm_name)
    rc, out = procs.peer(PROBE / "msg", "seq", "--seconds", str(SOAK_SECONDS), timeout=SOAK_SECONDS + 90)
    result = _result(rc, out)
    assert result["steps"] == {"10": result["count"] - 1}, result  # every step exactly the decimation
    assert abs(result["count"] - 100 * SOAK_SECONDS) <= 100, result  # 100 Hz, give or take a second
    assert bridge.terminate() == 0
    assert ", 0 lost in the ring" in bridge.output, bridge.output


def test_cpp_node_code_compiles_against_the_package(tmp_path):
    """A C++ node's use of the types (XRF2's includes and names) compiles against the installed
    package's headers (rclcpp is not on PyPI; the message code is what must not change)."""
    import shutil

    from xrflab.ros.interfaces import build_interface_package

    prefix = build_interface_package(RELBOT / "msg")
    src = tmp_path / "node.cpp"
    src.write_text(
        '#include "xrf2_msgs/msg/ros2_xeno.hpp"\n#include "xrf2_msgs/msg/xeno2_ros.hpp"\n#include <cstdio>\n'
        "int main() { xrf2_msgs::msg::Ros2Xeno m; m.steer_left = 1.5; m.steer_right = -0.5;\n"
        "  xrf2_msgs::msg::Xeno2Ros r; r.pos_left = m.steer_left; r.pos_right = m.steer_right;\n"
        '  std::printf("%g %g\\n", r.pos_left, r.pos_right); return m == xrf2_msgs::msg::Ros2Xeno() ? 1 : 0; }\n'
    )
    venv_include = Path(sys.prefix) / "include"
    includes = [f"-I{prefix / 'include' / 'xrf2_msgs'}"] + [
        f"-I{d}" for d in sorted(venv_include.iterdir()) if d.is_dir()
    ]
    cxx = shutil.which("g++") or shutil.which("c++")
    assert cxx, "no C++ compiler"
    r = subprocess.run(
        [cxx, "-std=c++17", *includes, str(src), "-o", str(tmp_path / "node")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    out = subprocess.run([str(tmp_path / "node")], capture_output=True, text=True, timeout=10)
    assert out.returncode == 0 and out.stdout.split() == ["1.5", "-0.5"], out
