"""Builds that misbehave fail cleanly in the sandbox with a message a student understands, and
leave nothing behind: no process of the build user, no file outside the build folder."""

from __future__ import annotations

import contextlib
import os
import pwd
import shutil
import subprocess
import time
import uuid
from pathlib import Path

import pytest

from xrf_testing.harness import wait_for
from xrf_testing.projects_support import wait_build
from xrflab.projects.builder import Builder, SandboxConfig
from xrflab.projects.store import ProjectStore

REPO = Path(__file__).resolve().parents[2]
BASE = REPO / "student_projects/templates/base"
ROOT = os.geteuid() == 0


def _builder(data_dir: Path, **cfg) -> tuple[Builder, ProjectStore, list]:  # noqa: ANN003
    store = ProjectStore(data_dir / "projects.sqlite3")
    root = data_dir / "projects"
    root.mkdir(exist_ok=True)
    os.chmod(root, 0o711)
    messages: list = []
    return (
        Builder(store, root, lambda t, p: messages.append(p), SandboxConfig(**cfg), hide_dir=data_dir),
        store,
        messages,
    )


def _project(store: ProjectStore, builder: Builder, cmakelists: str | None = None, edit: dict[str, str] | None = None):  # noqa: ANN202
    token = uuid.uuid4().hex[:12]
    folder = builder.projects_root / token
    folder.mkdir()
    os.chmod(folder, 0o755)
    shutil.copytree(BASE, folder / "src", ignore=shutil.ignore_patterns("build"))
    if cmakelists is not None:
        (folder / "src" / "CMakeLists.txt").write_text(cmakelists)
    for rel, text in (edit or {}).items():
        (folder / "src" / rel).write_text(text)
    return store.create_project("alice", "t", token, "upload"), folder / "src"


def _build(data_dir: Path, cmakelists: str | None = None, edit: dict[str, str] | None = None, **cfg):  # noqa: ANN003, ANN202
    builder, store, messages = _builder(data_dir, **cfg)
    project, src = _project(store, builder, cmakelists, edit)
    row, reused = builder.submit(project, src)
    assert not reused
    b = wait_build(store, row.id)
    log = Path(b.log_path).read_text()
    return b, log, messages, src


def _user_processes(under: Path) -> list[str]:
    """The build user's live processes working under `under` (this test's data folder): another
    test's build runs as the same user at the same time (tests/sandbox/test_limits.py), and its
    processes are not this build's leftovers."""
    try:
        uid = pwd.getpwnam("xrf-build").pw_uid
    except KeyError:
        return []
    # Killed processes whose parent was killed too wait for PID 1 to reap them: dead (Z) is gone.
    r = subprocess.run(["ps", "-u", str(uid), "-o", "stat=,pid=,cmd="], capture_output=True, text=True)
    found = []
    for ln in r.stdout.splitlines():
        if not ln.strip() or ln.strip().startswith("Z"):
            continue
        try:  # a build's processes work in its folder (the sandbox keeps the host's paths)
            cwd = Path(os.readlink(f"/proc/{ln.split()[1]}/cwd"))
        except OSError:
            continue  # gone meanwhile
        if cwd.is_relative_to(under.resolve()):
            found.append(ln)
    return found


def _no_user_processes_soon(under: Path) -> None:
    """The build's processes are gone: killed with the build, reaped a moment later."""
    with contextlib.suppress(AssertionError):
        wait_for(lambda: not _user_processes(under), 5, "the build user's processes to go")
    assert not _user_processes(under), _user_processes(under)


PRELUDE = "cmake_minimum_required(VERSION 3.16)\n"
TAIL = "project(p LANGUAGES C CXX)\nfind_package(XrfRt REQUIRED)\nxrf_add_controller(p SOURCES src/main.cpp src/Template.cpp INCLUDE_DIRS include)\n"


def test_ok_build_streams_and_is_sandboxed(data_dir: Path) -> None:
    b, log, messages, _ = _build(data_dir)
    assert b.status == "ok", log[-2000:]
    assert "sandbox: no network" in log
    assert "nice 19, SCHED_IDLE" in log
    if ROOT:
        assert "user xrf-build" in log
    assert any(m.get("line", "").startswith("[") for m in messages), "build lines are streamed"
    # The record is stored first, then announced: the final message may trail the store by a moment.
    with contextlib.suppress(AssertionError):
        wait_for(lambda: any(m.get("status") == "ok" for m in messages), 5, "the final message")
    assert [m["status"] for m in messages if "status" in m] == ["queued", "building", "ok"]
    assert Path(b.executable).is_file()
    assert b.toolchain.startswith("cmake version")


def test_download_fails_without_network(data_dir: Path) -> None:
    cml = (
        PRELUDE
        + (
            'file(DOWNLOAD "http://1.1.1.1/x" "${CMAKE_BINARY_DIR}/x" STATUS st TIMEOUT 5)\n'
            'list(GET st 0 code)\nif(NOT code EQUAL 0)\n  message(FATAL_ERROR "file DOWNLOAD failed: ${st}")\nendif()\n'
        )
        + TAIL
    )
    b, log, _, _ = _build(data_dir, cml)
    assert b.status == "failed"
    assert "no network" in b.result, b.result
    assert "CMakeLists.txt:" in b.result


def test_write_outside_build_folder_fails(data_dir: Path) -> None:
    marker = f"escape-{uuid.uuid4().hex[:8]}"
    cml = (
        PRELUDE
        + (
            f'file(WRITE "/tmp/{marker}" "x")\n'  # private tmpfs: vanishes with the build
            f'file(WRITE "${{CMAKE_SOURCE_DIR}}/../{marker}" "x")\n'
        )
        + TAIL
    )
    b, log, _, src = _build(data_dir, cml)
    assert b.status == "failed"
    assert "only write inside its own build folder" in b.result or "Permission denied" in log, b.result
    assert not (src.parent / marker).exists()
    assert not Path(f"/tmp/{marker}").exists()
    assert not (src / marker).exists()


def test_compile_error_has_file_and_line(data_dir: Path) -> None:
    text = (BASE / "src/Template.cpp").read_text()
    lines = text.splitlines()
    lines.insert(10, "int broken = undefined_name_here;")
    b, log, _, _ = _build(data_dir, edit={"src/Template.cpp": "\n".join(lines) + "\n"})
    assert b.status == "failed"
    assert b.result.startswith("src/Template.cpp:11:"), b.result
    assert "undefined_name_here" in b.result
    d = b.details["diagnostics"][0]
    assert d["file"] == "src/Template.cpp" and d["line"] == 11 and d["in_project"]


def test_link_error(data_dir: Path) -> None:
    text = (BASE / "src/Template.cpp").read_text() + "\nvoid never_defined();\nvoid call_it() { never_defined(); }\n"
    b, log, _, _ = _build(data_dir, edit={"src/Template.cpp": text})
    assert b.status == "failed"
    assert "undefined reference" in b.result and "never_defined" in b.result, b.result


def test_build_that_runs_forever_is_stopped(data_dir: Path) -> None:
    cml = PRELUDE + 'execute_process(COMMAND sh -c "sleep 1000 & sleep 1000")\n' + TAIL
    t0 = time.monotonic()
    b, log, _, _ = _build(data_dir, cml, timeout_s=4)
    assert time.monotonic() - t0 < 30
    assert b.status == "failed"
    assert "longer than 4 s" in b.result
    _no_user_processes_soon(data_dir)


@pytest.mark.skipif(not ROOT, reason="RLIMIT_NPROC counts the build user's processes: needs the dedicated user")
def test_fork_bomb_is_limited(data_dir: Path) -> None:
    # Forks until fork() fails; every child sleeps. The parent dies of the failed fork.
    cml = (
        PRELUDE
        + (
            'execute_process(COMMAND python3 -c "import os, time\\nwhile True:\\n    if os.fork() == 0: time.sleep(100)"'
            " COMMAND_ERROR_IS_FATAL ANY)\n"
        )
        + TAIL
    )
    b, log, _, _ = _build(data_dir, cml, nproc=64, timeout_s=30)
    assert b.status == "failed"
    assert "too many processes" in b.result, (b.result, log[-1500:])
    _no_user_processes_soon(data_dir)


def test_memory_eater_is_limited(data_dir: Path) -> None:
    cml = PRELUDE + ('execute_process(COMMAND python3 -c "x = bytearray(8 << 30)" COMMAND_ERROR_IS_FATAL ANY)\n') + TAIL
    b, log, _, _ = _build(data_dir, cml, memory_mb=512)
    assert b.status == "failed"
    assert "out of memory" in b.result, (b.result, log[-1500:])


def test_unchanged_source_reuses_build_and_builds_queue(data_dir: Path) -> None:
    builder, store, _ = _builder(data_dir)
    p1, s1 = _project(store, builder)
    p2, s2 = _project(store, builder)
    b1, r1 = builder.submit(p1, s1)
    b2, r2 = builder.submit(p2, s2)
    assert not r1 and not r2
    assert builder.position(b2.id) == 1  # queued behind b1: one build at a time
    b1, b2 = wait_build(store, b1.id), wait_build(store, b2.id)
    assert b1.status == b2.status == "ok"
    assert b2.started >= b1.ended - 0.01  # never in parallel
    again, reused = builder.submit(p1, s1)
    assert reused and again.id == b1.id
    (s1 / "README.md").write_text("changed\n")
    third, reused = builder.submit(p1, s1)
    assert not reused and third.id != b1.id
    wait_build(store, third.id)


def test_other_projects_and_the_data_folder_are_invisible(data_dir: Path) -> None:
    builder, store, _ = _builder(data_dir)
    _, other_src = _project(store, builder)
    (data_dir / "secret.sqlite3").write_text("grades")
    cml = (
        PRELUDE
        + (
            f'file(GLOB seen "{builder.projects_root}/*")\n'
            'message(STATUS "seen: ${seen}")\n'
            f'if(EXISTS "{other_src}/CMakeLists.txt" OR EXISTS "{data_dir}/secret.sqlite3")\n'
            '  message(FATAL_ERROR "LEAK")\nendif()\n'
            'file(WRITE "${CMAKE_SOURCE_DIR}/written.txt" "x")\n'
        )
        + TAIL
    )
    project, src = _project(store, builder, cml)
    row, _ = builder.submit(project, src)
    b = wait_build(store, row.id)
    log = Path(b.log_path).read_text()
    assert "LEAK" not in log, log[-2000:]
    seen = next(ln for ln in log.splitlines() if "seen: " in ln)
    assert other_src.parent.name not in seen and src.parent.name in seen, seen
    assert b.status == "failed" and "only write inside its own build folder" in b.result, b.result
    assert not (src / "written.txt").exists()
