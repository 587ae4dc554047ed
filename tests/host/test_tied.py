"""xrflab.tied: children die with the process that started them, a kill -9 included, even when
they were asked for from a thread that has ended since (PR_SET_PDEATHSIG follows the forking
thread, not the process)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from xrf_testing.harness import wait_for

REPO = Path(__file__).resolve().parents[2]

PARENT = r"""
import sys, threading, time
from xrflab.tied import popen_tied
out = {}
def ask():  # a short-lived worker thread, as the appliance's to_thread workers are
    out["child"] = popen_tied(["sleep", "60"])
t = threading.Thread(target=ask); t.start(); t.join()
print(out["child"].pid, flush=True)
time.sleep(60)
"""


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_a_tied_child_outlives_the_asking_thread_but_not_the_process() -> None:
    parent = subprocess.Popen(
        [sys.executable, "-c", PARENT],
        stdout=subprocess.PIPE,
        text=True,
        env=dict(os.environ, PYTHONPATH=str(REPO / "appliance")),
    )
    child = 0
    try:
        assert parent.stdout is not None
        child = int(parent.stdout.readline())
        time.sleep(0.3)  # the point: the asking thread has ended; the child must live on meanwhile
        assert _alive(child), "the child died with the thread that asked for it"
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
        with contextlib.suppress(AssertionError):
            wait_for(lambda: not _alive(child), 5, "the tied child to die")
        assert not _alive(child), "the child outlived its parent's kill -9"
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()
        if child and _alive(child):
            os.kill(child, signal.SIGKILL)
