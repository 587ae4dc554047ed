"""The fresh-machine check as one process tree tied to the test session: fresh_run.py started so
that everything it starts dies with pytest, can be killed as a whole, and can run at low priority
while the rest of the suite runs (`Background`, which tests/deploy/conftest.py registers, starts it
then; test_fresh_machine.py's fixture waits for it, or starts it itself when the check runs alone).

How it is tied to pytest:
- xrflab.tied.popen_tied (PR_SET_PDEATHSIG): the kernel kills the top process when pytest dies,
  however it dies;
- `unshare --pid --fork --kill-child=SIGKILL`: fresh_run.py is PID 1 of a PID namespace of its
  own, so when the top process dies, it and every process it started (cp, git, debootstrap, the
  tree's own namespace with apt, pip, chromium, the appliance) die with it;
- its own process group (not a session: a session would be its own scheduler autogroup, which
  nice cannot push below the suite), so the terminal's Ctrl-C reaches pytest only, which then
  cancels the run (`Background`) instead of half the tree receiving SIGINT.

Low priority (the background case): nice 19 and the idle I/O class, so the suite's timing tests are
disturbed as little as possible; `hurry()` gives every thread of the tree normal priority again
when the check's own tests start waiting for it (then nothing else of the suite is running).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from xrf_testing.leaks import descendants
from xrflab.tied import popen_tied

RUNNER = Path(__file__).resolve().parent / "fresh_run.py"
LOW = ["nice", "-n", "19", "ionice", "-c", "3"]
CONTAINED = ["unshare", "--pid", "--fork", "--kill-child=SIGKILL", "--"]


def _gone(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except (OSError, IndexError):
        return True


def _hurry(tree_pids: Callable[[], set[int]]) -> None:
    for _ in range(2):  # a process forked while the first pass ran is met by the second
        tids = []
        for pid in tree_pids():
            with contextlib.suppress(OSError):
                tids += [int(t) for t in os.listdir(f"/proc/{pid}/task")]
        for tid in tids:
            with contextlib.suppress(OSError):
                os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, 0))  # pytest's
        if tids:
            subprocess.run(
                ["ionice", "-c", "2", "-n", "4", "-p", *map(str, tids)],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )


def _record(result: Path, log_path: Path, ended: str) -> dict:
    """The record fresh_run.py wrote (its log's tail as the error if none)."""
    try:
        return json.loads(result.read_text())
    except (OSError, ValueError):
        log = log_path.read_text(errors="replace")[-4000:] if log_path.exists() else ""
        return {"error": f"fresh_run.py ended {ended} and no record:\n{log}"}


class Run:
    """fresh_run.py running on `dest` (its tree, its record, its log)."""

    def __init__(self, dest: Path, low_priority: bool, command: list[str] | None = None) -> None:
        self.dest = dest
        self.low = low_priority
        self.started = time.monotonic()
        self.result = dest / "result.json"
        self.log_path = dest / "runner.log"
        dest.mkdir(parents=True, exist_ok=True)
        command = command or [sys.executable, str(RUNNER), str(dest), str(self.result)]
        with open(self.log_path, "wb") as log:
            self.proc = popen_tied(
                [*(LOW if low_priority else []), *CONTAINED, *command],
                death_signal=signal.SIGKILL,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                process_group=0,
            )
        self.closed = False

    def tree_pids(self) -> set[int]:
        return {self.proc.pid, *descendants(self.proc.pid)} if self.proc.poll() is None else set()

    def hurry(self) -> None:
        """pytest's CPU priority and normal I/O priority for every thread of the tree (and so for what
        it starts next)."""
        if not self.low:
            return
        self.low = False
        _hurry(self.tree_pids)

    def wait(self) -> dict:
        """The record fresh_run.py wrote, once it has ended (its log's tail as the error if none)."""
        self.proc.wait()
        return _record(self.result, self.log_path, f"with {self.proc.returncode}")

    def seconds(self) -> float:
        return round(time.monotonic() - self.started, 1)

    def cancel(self, grace_s: float = 60.0) -> None:
        """Kill the whole tree and wait until none of it is left (the session's leak check follows)."""
        pids = self.tree_pids()
        if pids:
            with contextlib.suppress(OSError):
                os.killpg(self.proc.pid, signal.SIGKILL)
            for pid in pids:  # what left the group (setsid in the tree) dies with the namespace anyway
                with contextlib.suppress(OSError):
                    os.kill(pid, signal.SIGKILL)
        self.proc.wait()
        deadline = time.monotonic() + grace_s
        while not all(_gone(p) for p in pids) and time.monotonic() < deadline:
            time.sleep(0.1)

    def close(self) -> None:
        """Cancel if still running, then remove the tree copy (about 2 GB after the set-up). Idempotent."""
        if self.closed:
            return
        self.cancel()
        shutil.rmtree(self.dest, ignore_errors=True)
        self.closed = True


class Background:
    """The check's run, started with the session's first test and cancelled and removed before the
    session ends (then the leak check finds nothing of it: it is pytest's child, marked, and would)."""

    def __init__(self, config: pytest.Config) -> None:
        self.config = config
        self.run: Run | None = None
        self.claimed = False

    @pytest.hookimpl(tryfirst=True)
    def pytest_runtest_call(self, item: pytest.Item) -> None:
        # Not at collection: the first test's set-up is where tests/conftest.py's leak check takes
        # its snapshot of the processes; a run started before it would be invisible to the check.
        if self.run is None and not self.claimed:
            # pytest's own temporary folder (rotated by pytest should a killed session leave it)
            self.run = Run(self.config._tmp_path_factory.mktemp("fresh-machine"), low_priority=True)

    def claim(self) -> Run | None:
        """For the check's fixture: the background run (None if none started), never one later."""
        self.claimed = True
        return self.run

    # The run must be gone before the session fixtures are torn down (nothing_left_behind's check
    # among them). Both places where pytest does that are caught, before pytest's own hook:
    # the teardown of the last item, or of the failing one after -x/--maxfail (pytest then tears
    # down the whole stack there, nextitem=None); and session finish after Ctrl-C or an internal
    # error. When the check's tests ran, their fixture already closed it (close is idempotent).
    @pytest.hookimpl(tryfirst=True)
    def pytest_runtest_teardown(self, item: pytest.Item, nextitem: pytest.Item | None) -> None:
        if nextitem is None and self.run is not None:
            self.run.close()

    @pytest.hookimpl(tryfirst=True)
    def pytest_sessionfinish(self) -> None:
        if self.run is not None:
            self.run.close()


BACKGROUND = pytest.StashKey[Background]()


# With xdist workers (`./lab test`, the whole suite) no worker knows, when the session starts, which
# of them will get the check's tests, and a worker that started the run could end (and kill it)
# before the check's tests are reached elsewhere. So the controller, which runs no test and
# outlives every worker, starts the run with the session and closes it at its end (tests/conftest.py);
# the worker that reaches the check's tests attaches to it by the folder named in SHARED_ENV.
SHARED_ENV = "XRF_FRESH_SHARED"
FRESH_MODULE = Path(__file__).resolve().parents[1] / "deploy" / "test_fresh_machine.py"


def selected(config: pytest.Config) -> bool:
    """Whether the session's arguments take in the check (the controller collects nothing, so it
    reads them); a -k or -m that then leaves the check out only costs its cancelled run."""
    if os.geteuid() != 0 or not all(shutil.which(t) for t in ("unshare", "pivot_root", "nice", "ionice")):
        return False  # the check's fixture skips and says why
    args = [a.split("::", 1)[0] for a in config.args] or [str(config.rootpath)]
    for arg in args:
        path = Path(config.invocation_params.dir, arg).resolve()
        if path == FRESH_MODULE:
            return False  # the check alone: it runs in its fixture at normal priority, as always
        if FRESH_MODULE.is_relative_to(path):
            return True
    return False


def start_shared(config: pytest.Config) -> Run | None:
    """The controller's part: the run at low priority, its folder named for the workers."""
    if not selected(config):
        return None
    run = Run(config._tmp_path_factory.getbasetemp() / "fresh-machine", low_priority=True)
    (run.dest / "pid").write_text(f"{run.proc.pid} {run.started}")
    os.environ[SHARED_ENV] = str(run.dest)  # set before xdist starts its workers, who inherit it
    return run


class Attached:
    """The controller's run as the worker that reaches the check's tests sees it: it can raise its
    priority and wait for its record; the controller closes it."""

    def __init__(self, dest: Path) -> None:
        self.dest = dest
        pid, started = (dest / "pid").read_text().split()
        self.pid, self.started = int(pid), float(started)
        self.result, self.log_path = dest / "result.json", dest / "runner.log"
        self.low = True

    @classmethod
    def from_env(cls) -> Attached | None:
        dest = os.environ.get(SHARED_ENV)
        return cls(Path(dest)) if dest and Path(dest, "pid").exists() else None

    def tree_pids(self) -> set[int]:
        return set() if _gone(self.pid) else {self.pid, *descendants(self.pid)}

    def hurry(self) -> None:
        if self.low:
            self.low = False
            _hurry(self.tree_pids)

    def wait(self) -> dict:
        while not _gone(self.pid):  # the controller's child: gone is exited (a zombie until it reaps)
            time.sleep(1)  # polling: another process's child cannot be waited for
        return _record(self.result, self.log_path, "(its status is the controller's)")

    def seconds(self) -> float:
        return round(time.monotonic() - self.started, 1)

    def close(self) -> None:
        """Nothing: the run is the controller's, closed when its session ends."""
