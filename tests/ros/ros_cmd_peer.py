"""A separate ROS 2 node process driven line by line from stdin (one JSON reply per line), so a
test can interleave ROS 2 commands with appliance actions without rediscovering DDS each time.

    ready T      wait for a XenoCmd subscriber (the bridge) and a first XenoState
    cmd N        publish XenoCmd N
    wait N T     spin until the latest XenoState is N (fails after T s)
    hold T       spin T s; reply with the states seen meanwhile
"""

from __future__ import annotations

import json
import sys
import time

import rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Int32

QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


def main() -> int:
    rclpy.init()
    node = Node("xrf_test_cmd_peer")
    states: list[int] = []
    pub = node.create_publisher(Int32, "XenoCmd", QOS)
    node.create_subscription(Int32, "XenoState", lambda m: states.append(m.data), QOS)

    def spin_until(cond, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not cond():
            if time.monotonic() > deadline:
                return False
            rclpy.spin_once(node, timeout_sec=0.01)
        return True

    print(json.dumps({"ok": True, "hello": True}), flush=True)
    for line in sys.stdin:
        words = line.split()
        if not words:
            continue
        op, args = words[0], words[1:]
        if op == "ready":
            ok = spin_until(lambda: pub.get_subscription_count() > 0 and bool(states), float(args[0]))
            reply = {"ok": ok, "state": states[-1] if states else None}
        elif op == "cmd":
            pub.publish(Int32(data=int(args[0])))
            reply = {"ok": True}
        elif op == "wait":
            want = int(args[0])
            ok = spin_until(lambda want=want: bool(states) and states[-1] == want, float(args[1]))
            reply = {"ok": ok, "state": states[-1] if states else None, "recent": states[-10:]}
        elif op == "hold":
            start = len(states)
            spin_until(lambda: False, float(args[0]))
            reply = {"ok": True, "states": states[start:], "state": states[-1] if states else None}
        else:
            reply = {"ok": False, "error": f"unknown op {op}"}
        print(json.dumps(reply), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
