"""A stand-alone ROS 2 node, as a course node would be, for the bridge tests.

It imports xrf2_msgs exactly as an XRF2 node does (the test gives it PYTHONPATH etc. from
``xrflab.ros.interfaces.runtime_env``) and talks to the bridge over DDS only. Prints one JSON
object with what it saw on stdout.

    python ros_peer.py relbot --left 1.0 --right -0.5
    python ros_peer.py seq --seconds 60
    python ros_peer.py relbot --release v1.0     # the first XRF2 release's topics: Command, Xenomai_state
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import time

import rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Int32
from xrf2_msgs.msg import Ros2Xeno, Xeno2Ros

QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


# Command and state topics per XRF2 release (data topics are the same in both).
TOPICS = {"v1.1": ("XenoCmd", "XenoState"), "v1.0": ("Command", "Xenomai_state")}


class Peer(Node):
    def __init__(self, release: str = "v1.1") -> None:
        super().__init__("xrf_test_peer")
        cmd_topic, state_topic = TOPICS[release]
        self.states: list[int] = []
        self.samples: list[tuple[float, Xeno2Ros]] = []
        self.cmd_pub = self.create_publisher(Int32, cmd_topic, QOS)
        self.data_pub = self.create_publisher(Ros2Xeno, "Ros2Xeno", QOS)
        self.create_subscription(Int32, state_topic, lambda m: self.states.append(m.data), QOS)
        self.create_subscription(Xeno2Ros, "Xeno2Ros", lambda m: self.samples.append((time.monotonic(), m)), QOS)

    def spin_until(self, cond, timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not cond():
            if time.monotonic() > deadline:
                raise TimeoutError(f"timed out after {timeout:g} s waiting for {what}; states seen {self.states[-20:]}")
            rclpy.spin_once(self, timeout_sec=0.01)

    def send_cmd(self, cmd: int) -> None:
        m = Int32()
        m.data = cmd
        self.cmd_pub.publish(m)


def scenario_relbot(node: Peer, args: argparse.Namespace) -> dict:
    out: dict = {}
    node.spin_until(
        lambda: (
            node.cmd_pub.get_subscription_count() > 0 and node.data_pub.get_subscription_count() > 0 and node.states
        ),
        30,
        "the bridge (XenoCmd/Ros2Xeno subscribers, a XenoState)",
    )
    out["initial_state"] = node.states[-1]
    node.send_cmd(1)
    node.spin_until(lambda: node.states and node.states[-1] == 3, 10, "XenoState 3 after XenoCmd 1")
    node.send_cmd(2)
    node.spin_until(lambda: node.states and node.states[-1] == 4, 10, "XenoState 4 after XenoCmd 2")
    out["states"] = node.states[:]
    # Setpoints, republished at 50 Hz as a sequence controller would; Xeno2Ros must follow.
    start = len(node.samples)
    sp = Ros2Xeno(steer_left=args.left, steer_right=args.right)
    deadline = time.monotonic() + args.track_timeout
    settled_since = None
    while time.monotonic() < deadline:
        node.data_pub.publish(sp)
        t_end = time.monotonic() + 0.02
        while time.monotonic() < t_end:
            rclpy.spin_once(node, timeout_sec=0.005)
        if len(node.samples) > start:
            m = node.samples[-1][1]
            ok = abs(m.pos_left - args.left) < args.tol and abs(m.pos_right - args.right) < args.tol
            settled_since = (settled_since or time.monotonic()) if ok else None
            if settled_since and time.monotonic() - settled_since > 0.5:
                break
    got = node.samples[start:]
    out["tracking_samples"] = len(got)
    out["final"] = [got[-1][1].pos_left, got[-1][1].pos_right] if got else None
    out["settled"] = settled_since is not None
    out["first"] = [got[0][1].pos_left, got[0][1].pos_right] if got else None
    return out


def scenario_seq(node: Peer, args: argparse.Namespace) -> dict:
    node.spin_until(lambda: node.states, 30, "a XenoState from the bridge")
    node.spin_until(lambda: node.samples, 10, "the first Xeno2Ros")
    node.samples.clear()
    t_end = time.monotonic() + args.seconds
    while time.monotonic() < t_end:
        rclpy.spin_once(node, timeout_sec=0.05)
    cycles = [m.cycle for _, m in node.samples]
    steps: dict[int, int] = {}
    for a, b in zip(cycles, cycles[1:]):
        steps[b - a] = steps.get(b - a, 0) + 1
    return {
        "count": len(cycles),
        "first": cycles[:1],
        "last": cycles[-1:],
        "steps": {str(k): v for k, v in steps.items()},
    }


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("scenario", choices=["relbot", "seq"])
    parser.add_argument("--left", type=float, default=1.0)
    parser.add_argument("--right", type=float, default=-0.5)
    parser.add_argument("--tol", type=float, default=0.02)
    parser.add_argument("--track-timeout", type=float, default=15.0)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument(
        "--release", choices=sorted(TOPICS), default="v1.1", help="XRF2 release whose topic names to use"
    )
    args = parser.parse_args()
    signal.signal(signal.SIGTERM, lambda *a: sys.exit(2))
    rclpy.init()
    node = Peer(args.release)
    try:
        result = (scenario_relbot if args.scenario == "relbot" else scenario_seq)(node, args)
        result["ok"] = True
    except TimeoutError as exc:
        result = {"ok": False, "error": str(exc)}
    print(json.dumps(result), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0 if result["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
