"""The EVL build path on every CI run, against the EVL look-alike (tests/rt_core/evl/lookalike: a libevl
stand-in written here, not libevl): rt_core built with XRF_HAVE_EVL and installed, the RELbot
example and the 20-sim template built against the installed package by xrflab.build exactly as
`xrf build` does on a Pi (only XRF_EVL_PREFIX and XRF_CACHE_DIR point elsewhere), and run with
XRF_BACKEND=evl on the simulated board. The look-alike reports a stage switch wherever the EVL
core would (a plain system call or a signal handler on the attached thread, seen by a seccomp
filter), so status.demotions means here what it means on the Pi. docs/rt_core/evl.md.

Issue 16's faults, each with a test that fails without its fix: the package's interface lacking
libevl's include folder (the builds fail), the start banner after the stage-switch warnings were
switched on (one demotion per run), SIGTERM/SIGINT taken by the loop thread (one demotion), the
evl_init hints, and the refused doorbell writes not published.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from xrf_testing.loops import LoopProcess
from xrflab.build import BuildError, build_project
from xrflab.channels import lib

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[2]
LOOKALIKE = HERE / "lookalike"
PROJECTS = {
    "relbot": REPO / "student_projects/examples/relbot",
    "20sim": REPO / "student_projects/templates/20sim",
}
BANNER = "xrf: loop '"
WOSS_ON = "stage-switch warnings on (EVL_T_WOSS)"
# A switch the look-alike reported to the backend (SIGDEBUG: EVL_T_WOSS was on). Switches before
# that (the set-up's own warnings, e.g. SCHED_FIFO refused to a normal user) are not demotions.
SWITCH = "), SIGDEBUG"


@pytest.fixture(scope="session")
def evl_prefix(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The look-alike installed like libevl under /usr/evl: include/evl/*.h, lib/libevl.so."""
    prefix = tmp_path_factory.mktemp("evl-lookalike")
    subprocess.run(
        ["sh", str(LOOKALIKE / "build.sh"), str(prefix)], check=True, capture_output=True, text=True, timeout=120
    )
    return prefix


@pytest.fixture(scope="session")
def evl_builds(evl_prefix: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Each project's BuildResult, or the BuildError that stopped it (asserted in a test)."""
    work = tmp_path_factory.mktemp("evl-builds")
    out: dict = {}
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("XRF_EVL_PREFIX", str(evl_prefix))
        mp.setenv("XRF_CACHE_DIR", str(work / "cache"))
        for name, project in PROJECTS.items():
            try:
                out[name] = build_project(project, build_dir=work / name, log=lambda line: None)
            except BuildError as exc:
                out[name] = exc
    out["cache"] = work / "cache"
    return out


def _exe(evl_builds: dict, name: str) -> Path:
    r = evl_builds[name]
    if isinstance(r, BuildError):
        pytest.fail(f"{name} did not build against the EVL package: {r.message}\n{r.log_tail[-1500:]}")
    return r.executable


def _start(exe: Path, shm: str, cwd: Path, **env: str) -> LoopProcess:
    return LoopProcess(exe, shm, cwd, XRF_BACKEND="evl", XRF_QUIET="0", XRF_EVL_LOOKALIKE_TRACE="1", **env)


def _to_run(lp: LoopProcess, cycles: int = 200) -> None:
    lp.command("initialise", "INITIALISED", timeout=5)
    lp.command("start", "RUN", timeout=5)
    lp.wait_cycles(cycles, timeout=20)


def _stop(lp: LoopProcess) -> tuple[int, str]:
    """stop, quit, then the exit code and everything the process printed."""
    lp.command("stop", "STOPPED", timeout=5)
    assert lp.command("quit", timeout=5).accepted
    return lp.finish(timeout=20)


def test_controllers_build_against_the_installed_evl_package(evl_builds, evl_prefix):
    for name in PROJECTS:
        exe = _exe(evl_builds, name)
        needed = subprocess.run(["readelf", "-d", str(exe)], capture_output=True, text=True).stdout
        assert "libevl.so" in needed, f"{name} is not linked against libevl"
    # The installed package hands libevl's include folder on (fault 1: it was PRIVATE).
    targets = next(evl_builds["cache"].glob("rt_core/*/lib/cmake/XrfRt/XrfRtTargets.cmake")).read_text()
    assert "XRF_HAVE_EVL=1" in targets
    iface = next(line for line in targets.splitlines() if "INTERFACE_INCLUDE_DIRECTORIES" in line)
    assert str(evl_prefix / "include") in iface


@pytest.mark.parametrize("name", list(PROJECTS))
def test_default_run_counts_no_demotion_and_prints_before_going_out_of_band(evl_builds, name, shm_name, tmp_path):
    lp = _start(_exe(evl_builds, name), shm_name, tmp_path)
    try:
        assert lp.ch.info["backend"] == "evl"
        _to_run(lp)
        assert lp.ch.status().demotions == 0
        code, out = _stop(lp)
        st = lp.ch.status()
    finally:
        lp.stop()
    assert code == 0, out
    assert st.demotions == 0, out
    assert SWITCH not in out, out
    # The banner is written while stage-switch warnings are still off (fault 2).
    assert BANNER in out and WOSS_ON in out, out
    assert out.index(BANNER) < out.index(WOSS_ON), out


def test_switches_asked_for_are_counted_exactly(evl_builds, shm_name, tmp_path):
    lp = _start(_exe(evl_builds, "relbot"), shm_name, tmp_path, XRF_EVL_LOOKALIKE_DEMOTE="5")
    try:
        _to_run(lp)
        assert lp.ch.status().demotions == 5
        code, out = _stop(lp)
        st = lp.ch.status()
    finally:
        lp.stop()
    assert code == 0 and st.demotions == 5, out
    assert out.count(SWITCH) == 5, out


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_stop_signal_is_taken_in_band_and_stops_cleanly(evl_builds, sig, shm_name, tmp_path):
    lp = _start(_exe(evl_builds, "relbot"), shm_name, tmp_path)
    try:
        _to_run(lp)
        lp.proc.send_signal(sig)
        code, out = lp.finish(timeout=20)
        st = lp.ch.status()
        pwm = list(lp.ch.shm.sim.pwm)
    finally:
        lp.stop()
    assert code == 0, out
    assert not st.running and st.end_reason == lib.XRF_END_SIGNAL
    assert pwm == [0] * lib.XRF_MAX_CHANNELS
    # A handler run on the loop thread would have demoted it (fault 3).
    assert st.demotions == 0 and SWITCH not in out, out


@pytest.mark.parametrize(
    "err, hint",
    [
        ("EACCES", "/dev/evl/control"),
        ("EACCES", "group 'evl'"),
        ("ENOSYS", "no EVL core in this kernel"),
        ("ENOEXEC", "ABI mismatch between libevl and the kernel"),
    ],
)
def test_evl_init_failure_says_what_to_do(evl_builds, err, hint, shm_name, tmp_path):
    env = dict(os.environ, XRF_SHM=shm_name, XRF_BACKEND="evl", XRF_EVL_LOOKALIKE_INIT_ERRNO=err)
    proc = subprocess.run(
        [str(_exe(evl_builds, "relbot"))], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=30
    )
    assert proc.returncode != 0
    assert f"evl_init failed: {os.strerror(getattr(errno, err))}" in proc.stderr, proc.stderr
    assert hint in proc.stderr, proc.stderr


def _wait_doorbells(lp: LoopProcess, seconds: float) -> tuple[int, int]:
    """Host waits on the doorbell for `seconds`: (waits, waits woken before their 50 ms timeout)."""
    waits = woken = 0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        seen = lp.ch.doorbell
        t0 = time.monotonic()
        lp.ch.wait_doorbell(seen, 50)
        waits += 1
        woken += lp.ch.doorbell != seen and time.monotonic() - t0 < 0.045
    return waits, woken


def test_doorbell_through_the_proxy_and_refused_writes_published(evl_builds, shm_name, tmp_path):
    lp = _start(_exe(evl_builds, "relbot"), shm_name, tmp_path, XRF_EVL_LOOKALIKE_PROXY_REFUSE="4")
    try:
        _to_run(lp, cycles=50)
        waits, woken = _wait_doorbells(lp, 1.0)
        st = lp.ch.status()
        state = subprocess.run(
            [sys.executable, "-m", "xrflab.cli", "state", "--json", "--shm", shm_name],
            capture_output=True,
            text=True,
            timeout=30,
        )
        code, out = _stop(lp)
        end = lp.ch.status()
    finally:
        lp.stop()
    # The four refused rings are counted and published; later rings woke the host through
    # proxy -> eventfd -> relay -> futex.
    assert st.doorbell_dropped == 4
    assert state.returncode == 0, state.stderr
    assert json.loads(state.stdout)["doorbell_dropped"] == 4
    assert woken >= waits * 0.8, (waits, woken)
    assert code == 0 and end.demotions == 0, out


def test_no_refused_doorbell_by_default(evl_builds, shm_name, tmp_path):
    lp = _start(_exe(evl_builds, "relbot"), shm_name, tmp_path)
    try:
        _to_run(lp, cycles=50)
        waits, woken = _wait_doorbells(lp, 0.5)
        assert lp.ch.status().doorbell_dropped == 0
        assert woken >= waits * 0.8, (waits, woken)
    finally:
        lp.stop()
