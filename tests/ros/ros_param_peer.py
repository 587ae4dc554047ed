"""What `ros2 param list/describe/set` does, as a separate rclpy process: the parameter services
of the bridge node (rcl_interfaces' ListParameters, DescribeParameters, SetParameters,
GetParameters). Prints one JSON object: {"list", "describe", "set", "get"}.

    ros_param_peer.py NODE NAME=VALUE [NAME=VALUE ...] [--atomic]
"""

from __future__ import annotations

import json
import sys
import time

import rclpy
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import DescribeParameters, GetParameters, ListParameters, SetParameters, SetParametersAtomically
from rclpy.node import Node


def call(node: Node, srv_type, name: str, request, timeout: float = 20.0):  # noqa: ANN001, ANN201
    client = node.create_client(srv_type, name)
    deadline = time.monotonic() + timeout
    while not client.wait_for_service(timeout_sec=0.2):
        if time.monotonic() > deadline:
            raise SystemExit(f"no service {name}")
    future = client.call_async(request)
    rclpy.spin_until_future_complete(node, future, timeout_sec=timeout)
    return future.result()


def main() -> int:
    target, *assignments = sys.argv[1:]
    atomic = "--atomic" in assignments
    assignments = [a for a in assignments if a != "--atomic"]
    rclpy.init()
    node = Node("xrf_test_param_peer")
    out: dict = {}
    names = call(node, ListParameters, f"/{target}/list_parameters", ListParameters.Request()).result.names
    out["list"] = sorted(n for n in names if n != "use_sim_time")
    req = DescribeParameters.Request(names=out["list"])
    out["describe"] = {
        d.name: {
            "description": d.description,
            "range": [[r.from_value, r.to_value] for r in d.floating_point_range],
        }
        for d in call(node, DescribeParameters, f"/{target}/describe_parameters", req).descriptors
    }
    params = []
    for a in assignments:
        name, _, text = a.partition("=")
        params.append(
            Parameter(name=name, value=ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=float(text)))
        )
    if params:
        if atomic:
            res = call(
                node,
                SetParametersAtomically,
                f"/{target}/set_parameters_atomically",
                SetParametersAtomically.Request(parameters=params),
            ).result
            out["set"] = [{"successful": res.successful, "reason": res.reason}]
        else:
            res = call(node, SetParameters, f"/{target}/set_parameters", SetParameters.Request(parameters=params))
            out["set"] = [{"successful": r.successful, "reason": r.reason} for r in res.results]
    got = call(node, GetParameters, f"/{target}/get_parameters", GetParameters.Request(names=out["list"]))
    out["get"] = dict(zip(out["list"], [v.double_value for v in got.values], strict=True))
    print(json.dumps(out))
    node.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
