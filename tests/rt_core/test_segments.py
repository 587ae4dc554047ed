"""Whose shared-memory segment a host tool watches (issue 18): a loop re-creates its segment
under the same name, so `xrf state --wait` started while a new run comes up after a previous
one must follow the new object (it reported the previous run's STOPPED until it timed out);
`xrf cmd` does not send to an ended loop; `xrf run` removes its controller's segment when the
controller has exited (they piled up in /dev/shm)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from xrf_testing.harness import wait_for
from xrf_testing.loops import LoopProcess

SHM = Path("/dev/shm")


def xrf(*args: str, **kw) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2] / "appliance"))
    return subprocess.Popen(
        [sys.executable, "-m", "xrflab.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        **kw,
    )


def _maps(pid: int, shm: str) -> bool:
    """Process `pid` has /dev/shm/<shm> mapped (its status reader attached)."""
    try:
        return f"/dev/shm/{shm}" in Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return False


def previous_run_stopped(exe: Path, shm: str, cwd: Path) -> None:
    """A run driven to STOPPED, then ended by Ctrl-C: its segment stays (nothing removed it)."""
    lp = LoopProcess(exe, shm, cwd)
    lp.command("initialise", "INITIALISED")
    lp.command("start", "RUN")
    lp.command("stop", "STOPPED")
    lp.proc.send_signal(signal.SIGINT)
    code, out = lp.finish()
    lp.ch.close()
    assert code == 0, out
    assert (SHM / shm).exists()


def test_state_wait_follows_a_new_run_that_replaces_an_ended_one(
    probe_exe: Path, shm_name: str, tmp_path: Path
) -> None:
    previous_run_stopped(probe_exe, shm_name, tmp_path)
    old = (SHM / shm_name).stat().st_ino
    waiter = xrf("state", "--wait", "IDLE", "--timeout", "30", "--shm", shm_name)
    run = None
    try:
        # the waiter has the ended run's segment mapped (what the test is about: it must notice
        # the new run's segment replacing it)
        wait_for(lambda: _maps(waiter.pid, shm_name) or waiter.poll() is not None, 10, "the waiter to attach")
        assert waiter.poll() is None, waiter.communicate()
        run = xrf("run", str(probe_exe), "--shm", shm_name, start_new_session=True, cwd=tmp_path)
        out, err = waiter.communicate(timeout=40)
        assert waiter.returncode == 0, err
        assert out.strip() == "IDLE"
        assert "a new loop on shared memory" in err
        assert (SHM / shm_name).stat().st_ino != old
    finally:
        if run is not None:
            run.send_signal(signal.SIGINT)  # xrf run forwards it: the controller's safe stop
            run.communicate(timeout=20)
        if waiter.poll() is None:
            waiter.kill()
            waiter.communicate()
    assert run.returncode == 0
    # xrf run removed its controller's segment once it had exited.
    assert not (SHM / shm_name).exists()


def test_cmd_does_not_talk_to_an_ended_loop(probe_exe: Path, shm_name: str, tmp_path: Path) -> None:
    previous_run_stopped(probe_exe, shm_name, tmp_path)
    cmd = xrf("cmd", "initialise", "--shm", shm_name, "--timeout", "1")
    out, err = cmd.communicate(timeout=30)
    assert cmd.returncode == 1
    assert "has ended" in err and "state STOPPED" in err
    # Without --wait, `xrf state` shows the ended run's final state.
    state = xrf("state", "--shm", shm_name)
    assert state.communicate(timeout=30)[0].strip() == "STOPPED"


def test_echo_follows_the_next_run(probe_exe: Path, shm_name: str, tmp_path: Path) -> None:
    """`xrf echo XenoState` (XRF2's state topic, printed on each change) keeps printing across
    runs: INITIALISED can only come from the second loop, which the first never reached."""
    first = LoopProcess(probe_exe, shm_name, tmp_path)
    echo = xrf("echo", "XenoState", "--timeout", "60", "--shm", shm_name)
    second = None
    try:
        assert echo.stdout.readline().strip() == '{"data":1}'  # the first loop: IDLE
        first.proc.send_signal(signal.SIGINT)
        first.finish()
        first.ch.close()
        second = LoopProcess(probe_exe, shm_name, tmp_path)
        second.command("initialise", "INITIALISED")
        deadline = time.monotonic() + 30
        while (line := echo.stdout.readline().strip()) != '{"data":3}':
            assert line and time.monotonic() < deadline, f"echo stopped following: {line!r}"
    finally:
        echo.kill()
        err = echo.communicate()[1]
        if second is not None:
            second.stop()
    assert "a new loop on shared memory" in err
