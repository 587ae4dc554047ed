"""A build's end ends that build only: two builders (two appliances on one host, the same build
user) do not kill each other's builds, whatever a build left behind dies with it, and nothing is
left in the host's world-writable folders (/tmp, /var/tmp, /run/lock)."""

from __future__ import annotations

import contextlib
import os
import uuid
from pathlib import Path

from test_sandbox import PRELUDE, TAIL, _builder, _project

from xrf_testing.harness import wait_for
from xrf_testing.projects_support import reachable_tmp, wait_build
from xrflab.projects.build_procs import build_processes


def _processes_with(needle: str) -> list[str]:
    out = []
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            cmd = Path(f"/proc/{entry.name}/cmdline").read_bytes().replace(b"\0", b" ").decode()
            state = next(
                ln for ln in Path(f"/proc/{entry.name}/status").read_text().splitlines() if ln.startswith("State:")
            )
        except (OSError, StopIteration):
            continue
        if needle in cmd and "Z" not in state.split()[1]:
            out.append(f"{entry.name} {cmd}")
    return out


def _wait_log(store, bid: int, text: str, timeout: float = 120) -> None:
    def logged() -> bool:
        path = store.build(bid).log_path
        return bool(path) and os.path.exists(path) and text in Path(path).read_text()

    wait_for(logged, timeout, f"build {bid} to log {text!r}")


def test_one_builders_cleanup_spares_the_others_build(data_dir: Path) -> None:
    other_dir = reachable_tmp("data")
    try:
        builder_a, store_a, _ = _builder(data_dir)
        builder_b, store_b, _ = _builder(other_dir)
        # B: a build that takes a while (a sleep in CMake's configure step) and must succeed.
        slow = (
            PRELUDE
            + (
                'message(STATUS "b-is-sleeping")\n'
                "execute_process(COMMAND sleep 8 RESULT_VARIABLE rv)\n"
                'if(NOT rv EQUAL 0)\n  message(FATAL_ERROR "the sleep was killed: ${rv}")\nendif()\n'
            )
            + TAIL
        )
        project_b, src_b = _project(store_b, builder_b, slow)
        row_b, _ = builder_b.submit(project_b, src_b)
        _wait_log(store_b, row_b.id, "b-is-sleeping")
        # A: leaves a detached process behind (setsid + background) and fails at once; its
        # cleanup runs while B sleeps.
        marker = str(3000 + int(uuid.uuid4().int % 900))
        leaver = PRELUDE + (
            f'execute_process(COMMAND sh -c "setsid sleep {marker} >/dev/null 2>&1 < /dev/null &")\n'
            'message(FATAL_ERROR "a-is-done")\n'
        )
        project_a, src_a = _project(store_a, builder_a, leaver)
        row_a, _ = builder_a.submit(project_a, src_a)
        a = wait_build(store_a, row_a.id, timeout=60)
        assert a.status == "failed" and "a-is-done" in Path(a.log_path).read_text()
        assert store_b.build(row_b.id).status == "building", "B ended with A"
        # A's cleanup kills its tree as A ends; a moment for the kernel to reap it, no more
        with contextlib.suppress(AssertionError):
            wait_for(lambda: not _processes_with(f"sleep {marker}"), 5, "A's processes to go")
        assert not _processes_with(f"sleep {marker}"), "A's detached process outlived A"
        b = wait_build(store_b, row_b.id, timeout=300)
        log_b = Path(b.log_path).read_text()
        assert b.status == "ok", (b.result, log_b[-2000:])
        assert "own PID namespace" in log_b
        # Stopping builder A (an appliance shutting down) spares B's builds as well.
        project_b2, src_b2 = _project(store_b, builder_b, slow)
        row_b2, _ = builder_b.submit(project_b2, src_b2)
        _wait_log(store_b, row_b2.id, "b-is-sleeping")
        builder_a.stop()
        b2 = wait_build(store_b, row_b2.id, timeout=300)
        assert b2.status == "ok", b2.result
    finally:
        import shutil

        shutil.rmtree(other_dir, ignore_errors=True)


def test_nothing_is_left_in_world_writable_folders(data_dir: Path) -> None:
    marker = f"xrf-leak-{uuid.uuid4().hex[:8]}"
    folders = [d for d in ("/tmp", "/var/tmp", "/run/lock") if os.path.isdir(d)]
    before = {d: set(os.listdir(d)) for d in folders}
    writes = "".join(f'file(WRITE "{d}/{marker}" "x")\n' for d in folders)
    cml = PRELUDE + writes + 'message(STATUS "wrote-them")\n' + TAIL
    builder, store, _ = _builder(data_dir)
    project, src = _project(store, builder, cml)
    row, _ = builder.submit(project, src)
    b = wait_build(store, row.id)
    log = Path(b.log_path).read_text()
    assert "wrote-them" in log, log[-2000:]  # the writes succeeded, inside the sandbox
    assert b.status == "ok", b.result
    for d in folders:
        assert not os.path.exists(f"{d}/{marker}"), f"{d}/{marker} left behind"
        new = set(os.listdir(d)) - before[d]
        assert not any(marker in n for n in new), (d, new)
    assert not build_processes("no-such-token")
