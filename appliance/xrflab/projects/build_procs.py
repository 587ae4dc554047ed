"""Ending a build: exactly its processes, never another build's.

The appliance enforces a build's wall time: at the limit (and at the end of every build) it kills
the sandbox's process group, which takes the build's PID namespace with it (``sandbox.py``).
Where the kernel refused a PID namespace, it kills every process that carries this build's token
in its environment (``XRF_BUILD_TOKEN``, random per build), never all processes of the build
user: another appliance's build may run as the same user.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import threading
import time

TOKEN_ENV = "XRF_BUILD_TOKEN"


def build_processes(token: str) -> list[int]:
    """Pids of the processes that carry ``token`` (XRF_BUILD_TOKEN) in their environment: one
    build's, whichever appliance or user started them. Reading another user's environ needs root
    (as root builds run as the build user) or the same uid (without root builds run as ours)."""
    needle = f"{TOKEN_ENV}={token}".encode()
    found = []
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            with open(f"/proc/{entry.name}/environ", "rb") as f:
                env = f.read(1 << 20)
        except OSError:
            continue
        if needle in env.split(b"\0"):
            found.append(int(entry.name))
    return found


def kill_build_processes(token: str, rounds: int = 5) -> None:
    """SIGKILL every process of one build (by its token), again while some keep appearing (a
    fork racing the scan). Only needed where the kernel gave no PID namespace: with one, the
    sandbox's death has ended them all already and this finds nothing."""
    for _ in range(rounds):
        pids = build_processes(token)
        if not pids:
            return
        for pid in pids:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
        time.sleep(0.02)


def kill_build(proc: subprocess.Popen[str], token: str) -> None:
    """The sandbox's process group (and with it the PID namespace), then whatever carries the
    token: a build's background children or a fork bomb's remains."""
    with contextlib.suppress(OSError):
        os.killpg(proc.pid, signal.SIGKILL)
    kill_build_processes(token)


class RunningBuilds:
    """The sandboxes one builder has running, so that stopping it ends its builds only: another
    appliance's go on."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._procs: dict[int, tuple[subprocess.Popen[str], str]] = {}  # pid -> (sandbox, build token)

    def add(self, proc: subprocess.Popen[str], token: str) -> None:
        with self._lock:
            self._procs[proc.pid] = (proc, token)

    def remove(self, proc: subprocess.Popen[str]) -> None:
        with self._lock:
            self._procs.pop(proc.pid, None)

    def kill_all(self) -> None:
        with self._lock:
            procs = list(self._procs.values())
        for proc, token in procs:
            kill_build(proc, token)
