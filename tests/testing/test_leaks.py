"""The session's leftover check (xrf_testing/leaks.py) finds what it must and nothing else."""

from __future__ import annotations

import os
import subprocess
import sys
import uuid
from pathlib import Path

from xrf_testing.harness import wait_for
from xrf_testing.leaks import MARKER, NESTED_ENV, SHM, Snapshot


def test_it_finds_the_sessions_processes_and_shm_and_only_those(tmp_path: Path) -> None:
    repo = Path(__file__).resolve().parents[2]
    marker = uuid.uuid4().hex
    snap = Snapshot.take(marker, tmp_path, repo)
    env = {k: v for k, v in os.environ.items() if k != MARKER}
    marked = subprocess.Popen(["sh", "-c", "sleep 60 & wait"], env={**env, MARKER: marker}, start_new_session=True)
    launcher = subprocess.Popen(
        ["sleep", "60"], env={**env, "XRF_RUN_DIR": str(tmp_path / "runs" / "1")}, start_new_session=True
    )
    # Another session's process, not our child (its shell has exited: reparented away from us).
    out = subprocess.run(
        ["sh", "-c", "sleep 60 >/dev/null 2>&1 & echo $!"],
        env={**env, MARKER: "another-session"},
        capture_output=True,
        text=True,
        check=True,
    )
    stranger = int(out.stdout)
    shm = SHM / f"xrf-leak-check-{marker[:8]}"
    shm.write_bytes(b"x")
    try:
        wait_for(
            lambda: Path(f"/proc/{marked.pid}/task/{marked.pid}/children").read_text().strip(), 5, "the shell's child"
        )
        left = snap.leftovers(grace_s=0)
        pids = {int(line.split()[1].rstrip(":")) for line in left if line.startswith("process")}
        assert marked.pid in pids and launcher.pid in pids and stranger not in pids, left
        assert any(p != marked.pid and p != launcher.pid for p in pids), "the marked shell's child was missed"
        assert f"/dev/shm/{shm.name}" in left
        snap.clean()
        assert marked.wait(5) == -9 and launcher.wait(5) == -9 and not shm.exists()
        assert snap.leftovers(grace_s=1) == []
    finally:
        for p in (marked, launcher):
            if p.poll() is None:
                p.kill()
            p.wait()
        os.kill(stranger, 9)
        shm.unlink(missing_ok=True)


PLANTED = """
import os, time
from pathlib import Path


def test_one_worker_leaves_a_segment():
    Path("/dev/shm/{name}").write_bytes(b"x")


def test_the_other_worker_uses_one_and_cleans_up():
    p = Path("/dev/shm/{name}-used")
    p.write_bytes(b"x")
    p.unlink()
"""


def test_with_xdist_workers_the_controller_checks_once_at_the_end() -> None:
    """`./lab test` runs the suite in xdist workers; the leak check is then the controller's
    (tests/conftest.py): a real session with two workers whose test leaves a segment fails, names
    it, and removes it."""
    repo = Path(__file__).resolve().parents[2]
    name = f"xrf-leak-xdist-{uuid.uuid4().hex[:8]}"
    # in the checkout's tests/ so that its conftest applies; written before the session starts,
    # so it is not the session's leftover, and removed before ours ends
    planted = repo / "tests" / "testing" / f"test_planted_{name[-8:]}.py"
    planted.write_text(PLANTED.format(name=name))
    env = {k: v for k, v in os.environ.items() if k not in (MARKER, "PYTEST_XDIST_WORKER")}
    env[NESTED_ENV] = "xrf-leak-xdist-"  # beside this session's other workers (leaks.py)
    try:
        out = subprocess.run(
            [sys.executable, "-m", "pytest", "-n", "2", "--dist", "load", "-p", "no:cacheprovider", str(planted)],
            cwd=repo,
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )
    finally:
        planted.unlink()
    assert out.returncode == 1, out.stdout + out.stderr
    assert "2 passed" in out.stdout, out.stdout
    assert f"the test session left behind:\n  /dev/shm/{name}\n" in out.stderr, out.stderr
    assert not (SHM / name).exists()


def test_library_objects_left_by_design_are_reclaimed_once_nobody_maps_them(tmp_path: Path) -> None:
    """lttng-ust's wait page (made by every process that loads rclpy: the ROS 2 wheels bundle
    liblttng-ust) and Fast DDS's segments are removed at the session's end, but not while another
    process maps one (this one may: the session's own rclpy), and nothing else is."""
    import mmap

    repo = Path(__file__).resolve().parents[2]
    snap = Snapshot.take(uuid.uuid4().hex, tmp_path, repo)
    tag = uuid.uuid4().hex[:8]
    free, own, other, ours = (
        SHM / f"lttng-ust-wait-{tag}",
        SHM / f"lttng-ust-wait-{tag}-0",
        SHM / f"fastdds_{tag}",
        SHM / f"xrf-leak-{tag}",
    )
    for path in (free, own, other, ours):
        path.write_bytes(b"\0" * mmap.PAGESIZE)
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            f"import mmap, sys; f = open({str(other)!r}, 'r+b'); m = mmap.mmap(f.fileno(), 0); sys.stdin.read()",
        ],
        stdin=subprocess.PIPE,
    )
    try:
        with open(own, "r+b") as f, mmap.mmap(f.fileno(), mmap.PAGESIZE):
            wait_for(lambda: str(other) in Path(f"/proc/{holder.pid}/maps").read_text(), 10, "the holder's mapping")
            assert snap.reclaim_by_design() == sorted([free.name, own.name])
            assert not free.exists() and not own.exists() and other.exists() and ours.exists()
        holder.communicate(b"")  # it unmaps by exiting
        assert snap.reclaim_by_design() == [other.name]
        assert not other.exists()
    finally:
        holder.kill()
        holder.wait()
        for path in (free, own, other, ours):
            path.unlink(missing_ok=True)
