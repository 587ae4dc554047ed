"""What an upload is named and what the page is told before one (issue 31, friction):

- a ROS 2 workspace zipped the way students zip it has "src" (or "ws") as its top folder, so two
  students' projects were both called "src": the project is named after the controller package
  chosen in the workspace (its package.xml name), and the upload's answer and the project's
  detail say which package that is (not only the build log);
- a plain project keeps the archive's top folder as its name, and says no package;
- `xrf upload WORKSPACE` sends no name of its own (it sent the folder's, "ws"), so the same rule
  names it, and it says which package is built;
- what an upload may be and hold (formats, layouts, size limits) is served from the check's own
  definitions (projects/archive.py), not a copy in the page."""

from __future__ import annotations

import io
import os
import subprocess
import sys
import tarfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from xrf_testing.harness import Server, shared_builds_root, start_server, stop_server
from xrflab.projects import archive

REPO = Path(__file__).resolve().parents[2]
BASE = REPO / "student_projects/templates/base"
V11 = REPO / "tests/fixtures/xrf2_v1_1_project"
XRF2_MSGS_PACKAGE = (
    '<?xml version="1.0"?>\n<package format="3">\n  <name>xrf2_msgs</name>\n'
    "  <version>0.0.0</version>\n  <description>messages</description>\n"
    '  <maintainer email="s@example.org">s</maintainer>\n  <license>MIT</license>\n</package>\n'
)


def workspace_targz(top: str = "src", folder: str = "controller") -> bytes:
    """src/<folder> (the V1.1 fixture, package.xml name relbot_v11, no msg/), src/my_interfaces
    (the xrf2_msgs package with the messages), src/vision_node (another ROS 2 node): as a student
    packs `src/` of a colcon workspace."""
    buf = io.BytesIO()

    def add(name: str, data: bytes) -> None:
        info = tarfile.TarInfo(f"{top}/{name}")
        info.size = len(data)
        t.addfile(info, io.BytesIO(data))

    with tarfile.open(fileobj=buf, mode="w:gz") as t:
        for p in sorted(V11.rglob("*")):
            if not p.is_file() or "build" in p.relative_to(V11).parts:
                continue
            rel = p.relative_to(V11).as_posix()
            if rel.startswith("msg/"):
                add(f"my_interfaces/{rel}", p.read_bytes())
            else:
                add(f"{folder}/{rel}", p.read_bytes())
        add("my_interfaces/package.xml", XRF2_MSGS_PACKAGE.encode())
        add("vision_node/CMakeLists.txt", b"cmake_minimum_required(VERSION 3.8)\nproject(vision_node)\n")
        add("vision_node/package.xml", XRF2_MSGS_PACKAGE.replace("xrf2_msgs", "vision_node").encode())
    return buf.getvalue()


def project_targz(top: str) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as t:
        for p in sorted(BASE.rglob("*")):
            if p.is_file() and "build" not in p.relative_to(BASE).parts:
                info = tarfile.TarInfo(f"{top}/{p.relative_to(BASE).as_posix()}")
                info.size = p.stat().st_size
                t.addfile(info, io.BytesIO(p.read_bytes()))
    return buf.getvalue()


# ---- the archive check, in-process ---------------------------------------------------------------


def test_a_workspace_notes_the_controller_package_it_chose(tmp_path: Path) -> None:
    (tmp_path / "a.tar.gz").write_bytes(workspace_targz(folder="the_folder"))
    m = archive.unpack(tmp_path / "a.tar.gz", tmp_path / "out")
    assert m.prefix == "src"  # the top folder everyone's workspace has
    assert m.package == "the_folder"  # where it is, as the unpacked folder has it
    assert m.package_name == "relbot_v11"  # what it is called: its package.xml, not its folder


def test_a_plain_project_notes_no_package(tmp_path: Path) -> None:
    (tmp_path / "a.tar.gz").write_bytes(project_targz("my_base"))
    m = archive.unpack(tmp_path / "a.tar.gz", tmp_path / "out")
    assert (m.prefix, m.package, m.package_name) == ("my_base", "", "")


def test_the_rules_are_the_checks_own_limits() -> None:
    small = archive.Limits(max_upload=3 << 20, max_files=77)
    r = archive.rules(small)
    assert r["max_upload"] == 3 << 20 and r["max_files"] == 77
    assert r["formats"] == list(archive.SUFFIXES) and ".zip" in r["formats"]
    assert "build/" in r["left_out"]
    assert any("workspace" in x for x in r["layouts"]) and any("msg/Ros2Xeno.msg" in x for x in r["layouts"])


# ---- through the appliance ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def server(module_data_dir: Path) -> Iterator[Server]:
    s = start_server(module_data_dir, shared_builds_root())
    yield s
    stop_server(s)


def upload(http, data: bytes, name: str):  # noqa: ANN001, ANN201
    return http.post("/api/projects", files={"file": (name, data, "application/gzip")})


def test_two_workspaces_named_src_are_named_after_their_packages(server: Server) -> None:
    r = upload(server.http, workspace_targz(), "src.tar.gz")
    assert r.status_code == 201, r.text
    up = r.json()
    assert up["project"]["name"] == "relbot_v11", up
    assert up["stripped_folder"] == "src" and up["package"] == "controller"
    d = server.http.get(f"/api/projects/{up['project']['id']}").json()
    assert d["package"] == {"path": "controller", "name": "relbot_v11"}

    # a plain project: named after its folder, no package
    r = upload(server.http, project_targz("my_base"), "whatever.tar.gz")
    assert r.status_code == 201, r.text
    assert r.json()["project"]["name"] == "my_base" and r.json()["package"] == ""
    assert server.http.get(f"/api/projects/{r.json()['project']['id']}").json()["package"] is None


def test_the_upload_rules_are_served(server: Server) -> None:
    r = server.http.get("/api/project-upload-rules")
    assert r.status_code == 200, r.text
    assert r.json() == archive.rules(archive.Limits())


def test_xrf_upload_of_a_workspace_is_named_after_its_package(server: Server, tmp_path: Path) -> None:
    ws = tmp_path / "ws"
    with tarfile.open(fileobj=io.BytesIO(workspace_targz()), mode="r:gz") as t:
        t.extractall(ws, filter="data")  # ws/src/{controller,my_interfaces,vision_node}
    pw = server.create_user("naming_cli")
    tok = server.http.post("/api/auth/token", json={"username": "naming_cli", "password": pw})
    assert tok.status_code < 300, tok.text
    env = dict(os.environ, PYTHONPATH=str(REPO / "appliance"), XRF_TOKEN=tok.json()["token"])
    r = subprocess.run(
        [sys.executable, "-m", "xrflab.cli", "upload", str(ws), "--url", server.url],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert r.returncode == 0, (r.stdout, r.stderr)
    assert "(relbot_v11)" in r.stdout and "package controller/ is built" in r.stdout, r.stdout
