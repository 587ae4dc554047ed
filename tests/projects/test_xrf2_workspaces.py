"""XRF2 projects as students keep them, not as a tidy single folder (issue 17):

- the controller package has no msg/: XRF2 kept Ros2Xeno.msg / Xeno2Ros.msg in its xrf2_msgs
  package, XenoRosFramework/Common/XRF2_msgs/msg, in the framework folder the CMakeLists.txt
  names (../XRF2, ../ros2-xenomai4-framework) or as a package of its own in the workspace;
- a whole ROS 2 workspace is handed in (src/XRF2 with its Template/ projects, src/<controller>,
  other ROS nodes, a message package): the controller is the package that uses XRF2's loop;
- the CMakeLists.txt compiles a library from a sub-folder (add_subdirectory) and links it;
- Windows line endings everywhere, and a build/ folder committed from another machine.

The fixture projects (tests/fixtures/xrf2_v1_0_project, xrf2_v1_1_project) are rearranged
into those layouts here; the last test builds the worst of them with `xrf build` and drives it
to RUN on the simulated RELbot with the first release's command names."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from xrf_testing.loops import open_when_ready
from xrflab.build import BuildError, find_xrf2_controllers, plan_xrf2

REPO = Path(__file__).resolve().parents[2]
V10 = REPO / "tests/fixtures/xrf2_v1_0_project"
V11 = REPO / "tests/fixtures/xrf2_v1_1_project"
XRF2_MSGS_PACKAGE = """<?xml version="1.0"?>
<package format="3">
  <name>xrf2_msgs</name>
  <version>0.0.0</version>
  <description>messages between ROS 2 and the loop</description>
  <maintainer email="student@example.org">student</maintainer>
  <license>MIT</license>
  <buildtool_depend>ament_cmake</buildtool_depend>
  <member_of_group>rosidl_interface_packages</member_of_group>
</package>
"""


def xrf(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "xrflab.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=dict(os.environ, PYTHONPATH=str(REPO / "appliance")),
    )


def workspace(tmp: Path, fixture: Path, framework: str) -> tuple[Path, Path]:
    """ws/src/<framework>/XenoRosFramework/Common/XRF2_msgs/msg holds the messages (moved out of
    the project), ws/src/<project> the controller; returns (ws, project)."""
    ws = tmp / "ws"
    project = ws / "src" / fixture.name
    shutil.copytree(fixture, project)
    msgs = ws / "src" / framework / "XenoRosFramework" / "Common" / "XRF2_msgs"
    msgs.mkdir(parents=True)
    shutil.move(str(project / "msg"), str(msgs / "msg"))
    (msgs / "package.xml").write_text(XRF2_MSGS_PACKAGE)
    return ws, project


def test_messages_come_from_the_framework_folder_the_cmakelists_names(tmp_path: Path) -> None:
    ws, project = workspace(tmp_path, V10, "ros2-xenomai4-framework")
    plan = plan_xrf2(project)
    assert plan.msg_dir == (ws / "src/ros2-xenomai4-framework/XenoRosFramework/Common/XRF2_msgs/msg").resolve()
    assert any(t.endswith("XRF2_msgs/msg/Ros2Xeno.msg") for t in plan.taken), plan.taken


def test_messages_come_from_an_xrf2_msgs_package_in_the_workspace(tmp_path: Path) -> None:
    ws = tmp_path / "ws"
    project = ws / "src" / "controller"
    shutil.copytree(V11, project)
    package = ws / "src" / "my_interfaces"  # any folder name: the manifest says what it is
    package.mkdir()
    shutil.move(str(project / "msg"), str(package / "msg"))
    (package / "package.xml").write_text(XRF2_MSGS_PACKAGE)
    assert plan_xrf2(project).msg_dir == (package / "msg").resolve()


def test_no_messages_anywhere_says_where_it_looked(tmp_path: Path) -> None:
    project = tmp_path / "alone"
    shutil.copytree(V11, project)
    shutil.rmtree(project / "msg")
    with pytest.raises(BuildError) as e:
        plan_xrf2(project)
    assert "Ros2Xeno.msg and Xeno2Ros.msg not found" in e.value.message
    assert "XRF2/XenoRosFramework/Common/XRF2_msgs/msg" in e.value.message  # what the CMakeLists names


def test_the_controller_package_is_found_in_a_workspace(tmp_path: Path) -> None:
    ws, project = workspace(tmp_path, V11, "XRF2")
    # XRF2's own copy comes with Template/ projects that use its loop: not the student's controller.
    template = ws / "src/XRF2/Template/Template-Base"
    shutil.copytree(V10, template)
    node = ws / "src/vision_node"  # a ROS 2 node of the same workspace
    (node / "src").mkdir(parents=True)
    (node / "CMakeLists.txt").write_text(
        "cmake_minimum_required(VERSION 3.8)\nproject(vision_node)\n"
        "find_package(rclcpp REQUIRED)\nadd_executable(vision src/vision.cpp)\n"
    )
    (node / "src/vision.cpp").write_text("int main() { return 0; }\n")
    assert find_xrf2_controllers(ws) == [project]
    assert find_xrf2_controllers(ws / "src") == [project]
    second = ws / "src/old_controller"
    shutil.copytree(V10, second)
    assert find_xrf2_controllers(ws) == [second, project] or find_xrf2_controllers(ws) == [project, second]


def test_a_library_from_add_subdirectory_is_compiled(tmp_path: Path) -> None:
    project = tmp_path / "relbot"
    shutil.copytree(V11, project)
    _move_unwrap_into_a_library(project)
    plan = plan_xrf2(project)
    assert "src/util/Unwrap.cpp" in plan.taken, plan.taken
    assert "experiments/Broken.cpp" in plan.left_out


def _move_unwrap_into_a_library(project: Path) -> None:
    cml = project / "CMakeLists.txt"
    text = cml.read_text().replace("list(APPEND OWN_SOURCES src/util/Unwrap.cpp)\n", "add_subdirectory(src/util)\n")
    text = text.replace(
        "target_link_libraries(relbot_v11 evl pthread)", "target_link_libraries(relbot_v11 unwrap evl pthread)"
    )
    assert "add_subdirectory(src/util)" in text and " unwrap " in text
    cml.write_text(text)
    # Relative to the sub-folder, as CMake reads it.
    (project / "src/util/CMakeLists.txt").write_text("add_library(unwrap STATIC Unwrap.cpp)\n")


def _to_crlf(folder: Path) -> None:
    for f in folder.rglob("*"):
        if f.is_file() and f.suffix in (".cpp", ".hpp", ".h", ".txt", ".msg", ".xml"):
            f.write_bytes(f.read_bytes().replace(b"\r\n", b"\n").replace(b"\n", b"\r\n"))


def _state(shm: str, topic: str) -> int:
    r = xrf("echo", topic, "--count", "1", "--shm", shm, "--timeout", "5")
    assert r.returncode == 0, r.stdout + r.stderr
    return json.loads(r.stdout.splitlines()[0])["data"]


def test_a_workspace_with_everything_at_once_builds_and_runs(tmp_path: Path, shm_name: str) -> None:
    """The workspace handed in as it is: messages in ../ros2-xenomai4-framework, XRF2's
    Template/ and another ROS node beside the controller, a library from add_subdirectory,
    CRLF line endings, and a build/ folder (with a CMakeCache.txt) from another machine."""
    ws, project = workspace(tmp_path, V11, "ros2-xenomai4-framework")
    shutil.copytree(V10, ws / "src/ros2-xenomai4-framework/Template/Template-Base")
    node = ws / "src/vision_node"
    node.mkdir()
    (node / "CMakeLists.txt").write_text("cmake_minimum_required(VERSION 3.8)\nproject(vision_node)\n")
    (project / "CMakeLists.txt").write_text(
        (project / "CMakeLists.txt").read_text().replace("../XRF2/", "../ros2-xenomai4-framework/")
    )
    _move_unwrap_into_a_library(project)
    _to_crlf(ws)
    stale = ws / "build" / "cmake"
    stale.mkdir(parents=True)
    (stale / "CMakeCache.txt").write_text(
        "# from the student's Pi\nCMAKE_CACHEFILE_DIR:INTERNAL=/home/pi/ws/build/cmake\n"
        "CMAKE_HOME_DIRECTORY:INTERNAL=/home/pi/ws/build/xrf2-wrapper\n"
    )

    r = xrf("build", "--no-ros-messages", str(ws), timeout=600)
    assert r.returncode == 0, r.stderr[-4000:]
    log = r.stderr
    assert "building its XRF2 controller package src/xrf2_v1_1_project" in log, log[-3000:]
    assert "XRF2_msgs/msg/Ros2Xeno.msg" in log and "configuring afresh" in log, log[-3000:]
    exe = Path(r.stdout.strip().splitlines()[-1])

    proc = subprocess.Popen(
        [str(exe)],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=dict(
            os.environ, XRF_SHM=shm_name, XRF_SIM="relbot", XRF_TRANSPORT="sim", XRF_PRIO="0", XRF_LOG_DIR=str(tmp_path)
        ),
    )
    try:
        ch = open_when_ready(shm_name, proc)
        for cmd, want in (("initialise", 3), ("start", 4)):
            r = xrf("pub", "Command", cmd, "--shm", shm_name)
            assert r.returncode == 0 and "accepted" in r.stdout, r.stdout + r.stderr
            deadline = time.monotonic() + 5
            while (s := _state(shm_name, "Xenomai_state")) != want:
                assert time.monotonic() < deadline, f"state {s}, wanted {want}"
        # The messages taken from the framework folder are the ones the loop exchanges.
        r = xrf("echo", "Xeno2Ros", "--count", "1", "--shm", shm_name, "--timeout", "5")
        assert set(json.loads(r.stdout.splitlines()[0])) >= {"pos_left", "pos_right", "state"}, r.stdout
        for cmd in ("stop", "quit"):
            r = xrf("pub", "Command", cmd, "--shm", shm_name)
            assert r.returncode == 0 and "accepted" in r.stdout, r.stdout + r.stderr
        out = proc.communicate(timeout=20)[0]
        assert proc.returncode == 0, out
        ch.close()
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
            proc.communicate(timeout=5)
