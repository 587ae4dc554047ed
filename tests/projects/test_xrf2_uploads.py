"""XRF2 projects uploaded as students keep them (issue 17), through the real appliance: the upload
check takes the same rules as `xrf build` (build.locate_project), so

(a) a first-release controller package whose messages are in the XRF2 framework folder next to
    it (a workspace archive), and
(b) a workspace with several ROS 2 packages whose messages are an xrf2_msgs package

are accepted, build, run to RUN on the simulated RELbot, and the run's setpoint schema (what the
Bench page draws) is the resolved Ros2Xeno's fields; (c) an archive with messages nowhere is
refused (422) naming where it looked, and nothing is stored. The fixtures are rearranged as
tests/projects/test_xrf2_workspaces.py does."""

from __future__ import annotations

import io
import shutil
import tarfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from test_projects_api import run_to_run, upload

from xrf_testing.harness import Server, shared_builds_root, start_server, stop_server
from xrf_testing.projects_support import build_and_wait

REPO = Path(__file__).resolve().parents[2]
V10 = REPO / "tests/fixtures/xrf2_v1_0_project"
V11 = REPO / "tests/fixtures/xrf2_v1_1_project"
XRF2_MSGS_PACKAGE = (
    '<?xml version="1.0"?>\n<package format="3">\n  <name>xrf2_msgs</name>\n'
    "  <version>0.0.0</version>\n  <description>messages</description>\n"
    '  <maintainer email="s@example.org">s</maintainer>\n  <license>MIT</license>\n</package>\n'
)


@pytest.fixture(scope="module")
def server(module_data_dir: Path) -> Iterator[Server]:
    s = start_server(module_data_dir, shared_builds_root())
    yield s
    stop_server(s)


def tar_folder(folder: Path, top: str) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as t:
        t.add(folder, arcname=top)
    return buf.getvalue()


def v10_in_framework_workspace(tmp: Path) -> tuple[Path, Path]:
    """ws/src/relbot_v1 (no msg/) and ws/src/ros2-xenomai4-framework/XenoRosFramework/Common/
    XRF2_msgs/msg, the folder its CMakeLists.txt names; returns (ws, messages folder)."""
    ws = tmp / "ws"
    project = ws / "src" / "relbot_v1"
    shutil.copytree(V10, project)
    msgs = ws / "src/ros2-xenomai4-framework/XenoRosFramework/Common/XRF2_msgs"
    msgs.mkdir(parents=True)
    shutil.move(str(project / "msg"), str(msgs / "msg"))
    (msgs / "package.xml").write_text(XRF2_MSGS_PACKAGE)
    return ws, msgs / "msg"


def v11_in_ros_workspace(tmp: Path) -> tuple[Path, Path]:
    """ws/src/controller (no msg/), ws/src/my_interfaces (the xrf2_msgs package: any folder name,
    its package.xml says what it is), ws/src/vision_node (another ROS 2 node)."""
    ws = tmp / "ws"
    project = ws / "src" / "controller"
    shutil.copytree(V11, project)
    package = ws / "src" / "my_interfaces"
    package.mkdir()
    shutil.move(str(project / "msg"), str(package / "msg"))
    (package / "package.xml").write_text(XRF2_MSGS_PACKAGE)
    node = ws / "src" / "vision_node"
    (node / "src").mkdir(parents=True)
    (node / "CMakeLists.txt").write_text(
        "cmake_minimum_required(VERSION 3.8)\nproject(vision_node)\n"
        "find_package(rclcpp REQUIRED)\nadd_executable(vision src/vision.cpp)\n"
    )
    (node / "src/vision.cpp").write_text("int main() { return 0; }\n")
    (node / "package.xml").write_text(XRF2_MSGS_PACKAGE.replace("xrf2_msgs", "vision_node"))
    return ws, package / "msg"


def fields_of(msg_file: Path) -> list[dict]:
    from xrflab.msgdef import Codec, parse_msg_file

    return [{"name": f.name, "type": f.type, "count": f.count} for f in Codec(parse_msg_file(msg_file)).fields]


@pytest.mark.parametrize("layout", ["v1_0_framework_folder", "v1_1_xrf2_msgs_package"])
def test_xrf2_workspace_uploaded_built_and_run(server: Server, tmp_path: Path, layout: str) -> None:
    ws, msgs = (v10_in_framework_workspace if layout.startswith("v1_0") else v11_in_ros_workspace)(tmp_path)
    r = upload(server.http, tar_folder(ws, "ws"), "ws.tar.gz")
    assert r.status_code == 201, r.text
    pid = r.json()["project"]["id"]
    expected = fields_of(msgs / "Ros2Xeno.msg")
    detail = server.http.get(f"/api/projects/{pid}").json()
    assert detail["messages"]["Ros2Xeno"] == expected, detail["messages"]
    assert detail["messages"]["Xeno2Ros"] == fields_of(msgs / "Xeno2Ros.msg")
    b = build_and_wait(server.http, pid, timeout=600)
    assert b["status"] == "ok", (b["result"], server.http.get(f"/api/projects/{pid}/builds/{b['id']}/log").text[-3000:])
    assert b["details"]["messages"]["Ros2Xeno"] == expected
    server.stop_run()
    with server.ws() as ws_client:
        ws_client.send({"type": "subscribe", "topics": ["state", "run"]})
        run = run_to_run(server, server.http, ws_client, pid, b["id"])
        started = ws_client.wait_for(
            lambda m: m.get("type") == "run" and m.get("ros2xeno") and (m.get("run") or {}).get("id") == run["id"],
            seen=True,
        )
        # What the Bench page builds its setpoint controls from.
        assert [{"name": f["name"], "type": f["type"], "count": f.get("count") or 0} for f in started["ros2xeno"]] == [
            {**f, "count": f["count"] or 0} for f in expected
        ], started["ros2xeno"]
    server.stop_run()


def test_no_messages_anywhere_refused_saying_where_it_looked(server: Server, tmp_path: Path) -> None:
    ws, msgs = v10_in_framework_workspace(tmp_path)
    shutil.rmtree(msgs)
    root = server.data_dir / "projects"
    server.http.get("/api/projects")
    before = sorted(p.name for p in root.iterdir())
    r = upload(server.http, tar_folder(ws, "ws"), "ws.tar.gz")
    assert r.status_code == 422, r.text
    error = r.json()["detail"]["error"]
    assert "Ros2Xeno.msg and Xeno2Ros.msg not found" in error, error
    assert "Looked in: src/relbot_v1/msg, src/ros2-xenomai4-framework/XenoRosFramework/Common/XRF2_msgs/msg" in error, (
        error
    )
    assert str(server.data_dir) not in error  # the appliance's folders are not the student's business
    assert sorted(p.name for p in root.iterdir()) == before
    assert not any((root / ".incoming").iterdir())
