"""The session's leftover check (xrf_testing/leaks.py) finds what it must and nothing else."""

from __future__ import annotations

import os
import subprocess
import uuid
from pathlib import Path

from xrf_testing.harness import wait_for
from xrf_testing.leaks import MARKER, SHM, Snapshot


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
