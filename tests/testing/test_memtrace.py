"""memtrace (xrf_testing/memtrace.py): a process started with it starts tracing at the first
SIGUSR2 and writes a tracemalloc snapshot at each, and the comparison of two names the line whose
memory grew between them."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

from xrf_testing.harness import wait_for
from xrf_testing.memtrace import growth, snapshot_path

TESTS = Path(__file__).resolve().parents[1]

# A process that installs memtrace and, for each line on its stdin, keeps 2 MB more.
GROWER = """
import sys
from pathlib import Path
from xrf_testing.memtrace import install
install(Path(sys.argv[1]))
kept = []
print("ready", flush=True)
for line in sys.stdin:
    kept.append(bytearray(2_000_000))  # the growth
    print("grown", flush=True)
"""


def test_snapshots_on_the_signal_and_the_growing_line_first(tmp_path: Path) -> None:
    folder = tmp_path / "snaps"  # made by install
    proc = subprocess.Popen(
        [sys.executable, "-c", GROWER, str(folder)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(TESTS)},
    )
    assert proc.stdin is not None and proc.stdout is not None
    try:
        assert proc.stdout.readline().strip() == "ready"
        proc.stdin.write("before tracing\n")  # kept before the first signal: not traced, not growth
        proc.stdin.flush()
        assert proc.stdout.readline().strip() == "grown"
        proc.send_signal(signal.SIGUSR2)
        wait_for(lambda: snapshot_path(folder, 0).is_file(), 30, "the first snapshot")
        for _ in range(3):
            proc.stdin.write("grow\n")
            proc.stdin.flush()
            assert proc.stdout.readline().strip() == "grown"
        proc.send_signal(signal.SIGUSR2)
        wait_for(lambda: snapshot_path(folder, 1).is_file(), 30, "the second snapshot")
        assert not list(folder.glob("*.part"))  # renamed into place, none half-written
        lines = growth(snapshot_path(folder, 0), snapshot_path(folder, 1))
        assert lines, "no growth found"
        # 3 x 2 MB held by the line marked "the growth" (line 9 of the script), reported first.
        kib = float(lines[0].split(" KiB", 1)[0])
        assert 5800 < kib < 6100, lines[0]
        assert 'File "<string>", line 9' in lines[0], lines[0]
        # Nothing else grew by a comparable amount.
        assert all(float(ln.split(" KiB", 1)[0]) < 1000 for ln in lines[1:]), lines
    finally:
        proc.stdin.close()
        proc.wait(30)
    assert proc.returncode == 0
