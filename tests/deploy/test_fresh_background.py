"""The fresh-machine check's background run (fresh_background.py, tests/deploy/conftest.py): it
runs last, at low priority until its tests wait for it, and whatever ends the session - its end,
-x after an early failure, Ctrl-C, pytest killed - nothing of it is left: no process, no tree copy,
and the session's own leak check (tests/conftest.py) finds nothing.

The session cases are real pytest sessions with the real check (its run is cut short while it
copies the tree or just after): a small plugin (written to tmp_path, loaded with -p) makes the
first test fail, interrupts the session or kills pytest once the run is under way.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from xrf_testing.fresh_background import Run
from xrf_testing.leaks import NESTED_ENV

REPO = Path(__file__).resolve().parents[2]
FIRST = "tests/doctor/test_doctor.py::test_evl_ok"  # a quick test to be the session's first
FRESH = "tests/deploy/test_fresh_machine.py"

# The ordering holds for everyone; the rest needs root, as the check itself does.
root_only = pytest.mark.skipif(os.geteuid() != 0, reason="the fresh-machine check runs as root only")

# The stand-in for fresh_run.py in the Run tests: a tree like the check's (a child in a process
# group of its own, a grandchild in a PID namespace of its own); a file says when it is up.
TREE = textwrap.dedent("""
    import subprocess, sys, time
    a = subprocess.Popen(["sleep", "1000"], start_new_session=True)
    b = subprocess.Popen(["unshare", "--pid", "--fork", "sleep", "1000"])
    time.sleep(0.5)
    open(sys.argv[1], "w").write("up")
    time.sleep(1000)
""")


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def _nice(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[16])


def _io_class(pid: int) -> str:
    return subprocess.run(["ionice", "-p", str(pid)], capture_output=True, text=True).stdout.split(":")[0].strip()


def _stand_in(tmp_path: Path, low: bool) -> tuple[Run, set[int]]:
    pids = tmp_path / "pids"
    run = Run(tmp_path / "run", low_priority=low, command=[sys.executable, "-c", TREE, str(pids)])
    deadline = time.monotonic() + 30
    while not pids.exists() or not pids.read_text():
        assert time.monotonic() < deadline, (tmp_path / "run/runner.log").read_text()
        time.sleep(0.1)
    tree = run.tree_pids()
    # unshare, the program, sleep (own group), unshare, and its namespace's sleep
    assert len(tree) == 5, [Path(f"/proc/{p}/cmdline").read_bytes() for p in tree]
    return run, tree


@root_only
def test_close_kills_the_whole_tree_and_removes_its_folder(tmp_path: Path) -> None:
    run, tree = _stand_in(tmp_path, low=False)
    run.close()
    assert not [p for p in tree if _alive(p)]
    assert not run.dest.exists()
    run.close()  # idempotent: the fixture and the session's end may both close it


@root_only
def test_low_priority_until_hurried(tmp_path: Path) -> None:
    run, tree = _stand_in(tmp_path, low=True)
    try:
        assert {_nice(p) for p in tree} == {19}
        assert {_io_class(p) for p in tree} == {"idle"}
        run.hurry()
        assert {_nice(p) for p in tree} == {os.getpriority(os.PRIO_PROCESS, 0)}
        assert {_io_class(p) for p in tree} == {"best-effort"}
    finally:
        run.close()


def test_the_check_is_ordered_last() -> None:
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "--collect-only",
            "-q",
            "-p",
            "no:cacheprovider",
            FRESH,
            "tests/doctor/test_doctor.py",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    ).stdout
    ids = [line for line in out.splitlines() if "::" in line]
    fresh = [i for i in ids if i.startswith(FRESH)]
    assert len(fresh) >= 5 and len(ids) > len(fresh), out
    assert ids[-len(fresh) :] == fresh, ids


# The inner session's plugin: once the first test has run, wait until the check's run is copying
# the tree (a `cp` under fresh_run.py), write every pid of it to a file, then end as told.
PLUGIN = textwrap.dedent("""
    import os, signal, sys, time
    from pathlib import Path
    import pytest

    HOW, PIDS = os.environ["XRF_TEST_HOW"], Path(os.environ["XRF_TEST_PIDS"])

    @pytest.hookimpl(wrapper=True)
    def pytest_runtest_call(item):
        result = yield
        if "test_fresh_machine" in item.nodeid:
            return result
        from xrf_testing.leaks import _cmdline, descendants  # importable once tests/conftest.py is
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            tree = descendants(os.getpid())
            if any(_cmdline(p).startswith("cp -a") for p in tree):
                break
            time.sleep(0.2)
        PIDS.write_text("".join(f"{p} {_cmdline(p)}\\n" for p in tree))
        if HOW == "interrupt":
            # Ctrl-C as in a terminal. A session started in the background by a non-interactive
            # shell (`.ci/run &`) inherits SIGINT ignored, and Python then installs no handler:
            # the signal would be lost and the test would measure the shell, not the clean-up.
            signal.signal(signal.SIGINT, signal.default_int_handler)
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)
        if HOW == "kill":
            os.kill(os.getpid(), signal.SIGKILL)
        raise AssertionError("the session's first test fails (-x stops the session)")
""")


@root_only
@pytest.mark.timeout(600)
@pytest.mark.parametrize("how", ["fail", "interrupt", "kill"])
def test_nothing_is_left_when_the_session_stops_early(tmp_path: Path, how: str) -> None:
    (tmp_path / "plugin").mkdir()
    (tmp_path / "plugin/xrf_stop_early.py").write_text(PLUGIN)
    basetemp, pids = tmp_path / "inner", tmp_path / "pids"
    # A session of its own: its own leak-check marker (not this session's, whose processes it
    # would otherwise count as its own), its own temporary folder.
    env = {k: v for k, v in os.environ.items() if k != "XRF_TEST_SESSION"}
    env[NESTED_ENV] = "xrf-fresh-nested-"  # beside this session's other workers: none of theirs (leaks.py)
    env.update(PYTHONPATH=str(tmp_path / "plugin"), XRF_TEST_HOW=how, XRF_TEST_PIDS=str(pids))
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-x",
            "-q",
            "-p",
            "xrf_stop_early",
            "-p",
            "no:cacheprovider",
            f"--basetemp={basetemp}",
            FIRST,
            FRESH,
        ],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=500,
    )
    out = proc.stdout + proc.stderr
    assert pids.exists(), out
    seen = dict(line.split(" ", 1) for line in pids.read_text().splitlines())
    tree = {int(p) for p in seen}
    assert any("fresh_run.py" in c for c in seen.values()), (seen, out)  # the run was under way
    assert any(c.startswith("cp -a") for c in seen.values()), (seen, out)
    deadline = time.monotonic() + 30
    while [p for p in tree if _alive(p)] and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not [p for p in tree if _alive(p)], out
    if how == "kill":
        assert proc.returncode == -9, out
        shutil.rmtree(basetemp, ignore_errors=True)  # pytest gets no chance to; its tree copy stays
        return
    assert proc.returncode == (1 if how == "fail" else 2), out
    assert "left behind" not in out, out
    assert not list(basetemp.glob("fresh-machine*")), out
