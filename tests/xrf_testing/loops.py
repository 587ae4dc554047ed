"""A controller executable running as a real process on its own shared memory, and the loop
probe fixture project built once per session."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

from xrflab.build import build_project
from xrflab.channels import Channels

REPO = Path(__file__).resolve().parents[2]
LOOP_PROBE = REPO / "tests/fixtures/loop_probe"


def build_probe(out: Path) -> Path:
    return build_project(LOOP_PROBE, build_dir=out, log=lambda line: None).executable


def open_when_ready(shm: str, proc: subprocess.Popen, timeout: float = 10.0) -> Channels:
    """The channels of loop process `proc` once its shared memory `shm` is ready (a leftover
    object of the same name from an earlier process is skipped by its pid)."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            ch = Channels.open(shm, wait_s=0.5)
            if ch.info["pid"] == proc.pid:
                return ch
            ch.close()
        except Exception:
            pass
        if proc.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"loop did not come up (exit {proc.poll()})")
        time.sleep(0.02)


class LoopProcess:
    """Starts `exe` with XRF_SHM=shm (plus `env`) and waits until its shared memory is ready.
    `capture=True` keeps its output for finish(); otherwise it is discarded."""

    def __init__(self, exe: Path, shm: str, cwd: Path, *, capture: bool = True, **env: str) -> None:
        self.shm = shm
        full_env = dict(os.environ, XRF_SHM=shm, **{k: str(v) for k, v in env.items()})
        out = subprocess.PIPE if capture else subprocess.DEVNULL
        self.proc = subprocess.Popen([str(exe)], cwd=cwd, env=full_env, stdout=out, stderr=subprocess.STDOUT, text=True)
        try:
            self.ch = open_when_ready(shm, self.proc)
        except RuntimeError as exc:
            output = self.proc.communicate(timeout=5)[0] if capture else ""
            raise RuntimeError(f"{exc}:\n{output}") from None

    def command(self, cmd: str | int, state: str | None = None, timeout: float = 3.0):
        """Send `cmd`; with `state`, also require it accepted and wait until the loop is there."""
        result = self.ch.wait_command(self.ch.send_command(cmd), timeout=timeout)
        if state is not None:
            assert result.accepted, f"{cmd}: {result.reason}"
            self.wait_state(state, timeout)
        return result

    def wait_state(self, name: str, timeout: float = 3.0) -> None:
        deadline = time.monotonic() + timeout
        while self.ch.status().state_name != name:
            if time.monotonic() > deadline:
                raise AssertionError(f"state {self.ch.status().state_name}, wanted {name}")
            time.sleep(0.005)

    def wait_cycles(self, n: int, timeout: float = 5.0) -> None:
        target = self.ch.status().cycles + n
        deadline = time.monotonic() + timeout
        while self.ch.status().cycles < target:
            if time.monotonic() > deadline:
                raise AssertionError("the loop stopped cycling")
            time.sleep(0.005)

    def finish(self, timeout: float = 10.0) -> tuple[int, str]:
        out = self.proc.communicate(timeout=timeout)[0]
        return self.proc.returncode, out or ""

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.communicate(timeout=5)
        self.ch.close()
