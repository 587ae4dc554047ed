"""Projects XRF Lab should accept or explain (issue 31): a CMake error's summary carries CMake's
message, and a project of the framework before XRF2 is recognised before CMake runs.

Real CMake configures (rt_core from the build cache), real files in the layouts students have.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from xrflab import build
from xrflab.projects.diagnostics import parse_diagnostics, summarise
from xrflab.projects.sandbox_config import SandboxConfig

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "std_types_controller"


def test_cmake_error_summary_shows_the_message_not_only_its_head(tmp_path: Path) -> None:
    """XrfController.cmake stops the configure with message(FATAL_ERROR): the one-line summary
    (the build page's result, `xrf build`'s error, the catalog's) shows the message itself."""
    project = tmp_path / "proj"
    shutil.copytree(FIXTURE, project)
    with open(project / "msg" / "Ros2Xeno.msg", "a") as f:
        f.write("string name\n")
    lines: list[str] = []
    with pytest.raises(build.BuildError) as err:
        build.build_project(project, tmp_path / "build", log=lines.append)
    assert any(line.startswith("CMake Error at ") and "XrfController.cmake" in line for line in lines), lines
    message = err.value.message
    assert message.startswith("configure failed (exit 1): "), message
    # CMake wraps the text at 80 columns over several indented lines: all of it, folded into one.
    assert "Ros2Xeno.msg:5: 'string name': an unbounded string cannot be carried by the loop's" in message
    assert "use a bounded one, string<=N (N bytes at most)" in message
    assert "the message files in" in message and "are not valid" in message
    assert "Call Stack" not in message

    diags = parse_diagnostics(lines, project, tmp_path / "build")
    first = next(d for d in diags if d["kind"] == "error")
    assert first["source"] == "cmake" and "an unbounded string cannot be carried" in first["message"]
    summary = summarise(False, lines, diags, SandboxConfig(), False, message, 1.0)
    assert "XrfController.cmake" in summary and "use a bounded one, string<=N" in summary, summary


def test_cmake_message_folds_paragraphs_and_stops_at_the_call_stack() -> None:
    lines = [
        "-- Configuring",
        "CMake Error at CMakeLists.txt:7 (message):",
        "  first part of a long",
        "  sentence",
        "",
        "  second paragraph",
        "Call Stack (most recent call first):",
        "  CMakeLists.txt:9 (include)",
        "CMake Error: The source directory /x does not exist.",
    ]
    assert build.cmake_message(lines, 1) == "first part of a long sentence second paragraph"
    assert build.cmake_message(lines, 8) == "The source directory /x does not exist."
    assert build.first_cmake_error(lines) == "first part of a long sentence second paragraph"
    assert build.first_cmake_error(["-- all fine"]) == ""


def _pre_xrf2_project(root: Path) -> Path:
    """A small controller in the older framework's layout: a class deriving from Native20Sim with
    preProc()/postProc(), messages from a custom_msgs package."""
    (root / "include").mkdir(parents=True)
    (root / "src").mkdir()
    (root / "CMakeLists.txt").write_text(
        "cmake_minimum_required(VERSION 3.5)\nproject(old_controller)\n"
        "find_package(ament_cmake REQUIRED)\nfind_package(rclcpp REQUIRED)\n"
        "find_package(custom_msgs REQUIRED)  # the old framework's messages\n"
        "add_executable(old_controller src/main.cpp src/MyApp.cpp)\n"
        "ament_target_dependencies(old_controller rclcpp custom_msgs)\nament_package()\n"
    )
    (root / "include" / "MyApp.h").write_text(
        '#pragma once\n#include "Native20Sim.h"\n\nclass MyApp : public Native20Sim\n{\npublic:\n'
        "    MyApp();\nprotected:\n    int preProc() override;\n    int postProc() override;\n};\n"
    )
    (root / "src" / "MyApp.cpp").write_text(
        '#include "MyApp.h"\nMyApp::MyApp() {}\nint MyApp::preProc() { u[0] = 1.0; return 0; }\n'
        "int MyApp::postProc() { return 0; }\n"
    )
    (root / "src" / "main.cpp").write_text('#include "MyApp.h"\nint main() { MyApp app; return app.run(); }\n')
    return root


def test_pre_xrf2_project_is_recognised_before_cmake(tmp_path: Path) -> None:
    project = _pre_xrf2_project(tmp_path / "old_controller")
    lines: list[str] = []
    with pytest.raises(build.BuildError) as err:
        build.build_project(project, tmp_path / "build", log=lines.append)
    message = err.value.message
    assert message.startswith("old_controller: this project is written for the framework before XRF2 ("), message
    assert "include/MyApp.h:4 derives from Native20Sim" in message
    assert "CMakeLists.txt: find_package(custom_msgs)" in message
    # What to change, in the student's terms.
    for words in (
        "XenoFrt20Sim instead of Native20Sim",
        "XenoFrtRosIco instead of NativeBase",
        "preProc()",
        "msg/Ros2Xeno.msg",
        "msg/Xeno2Ros.msg",
        "xrf new",
    ):
        assert words in message, words
    # Before CMake: nothing was configured (it used to stop at find_package(custom_msgs)).
    assert not any(line.startswith("$ cmake") for line in lines), lines
    assert not (tmp_path / "build" / "CMakeCache.txt").exists()

    # The upload check (locate_project) and a whole workspace say the same.
    with pytest.raises(build.BuildError, match="framework before XRF2"):
        build.locate_project(project)
    ws = tmp_path / "ws"
    _pre_xrf2_project(ws / "src" / "old_ws_controller")
    with pytest.raises(build.BuildError, match=r"old_ws_controller: this project is written for the framework before"):
        build.build_project(ws, tmp_path / "build-ws", log=lines.append)


def test_xrf2_projects_are_not_taken_for_the_old_framework(tmp_path: Path) -> None:
    repo = Path(__file__).resolve().parents[2]
    for example in ("student_projects/examples/relbot", "student_projects/templates/20sim"):
        assert build.pre_xrf2_evidence(repo / example) == [], example
    # An XRF2 project that kept an old file around is XRF2.
    project = _pre_xrf2_project(tmp_path / "mixed")
    (project / "src" / "Loop.cpp").write_text('#include "XenoFrtRosIco.hpp"\nclass L : public XenoFrtRosIco {};\n')
    assert build.pre_xrf2_evidence(project) == []
