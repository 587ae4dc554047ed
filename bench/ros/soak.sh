#!/bin/sh
# The 60 s soak of the ROS 2 bridge: tests/ros/test_bridge.py's no-loss test at full length (the
# suite runs it for 15 s). Every Xeno2Ros sample at 100 Hz reaches a separate rclpy node, no gap.
set -eu
cd "$(dirname "$0")/../.."
XRF_ROS_SOAK_SECONDS="${XRF_ROS_SOAK_SECONDS:-60}" exec ./lab test tests/ros/test_bridge.py -k soak -s "$@"
