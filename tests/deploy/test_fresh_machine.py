"""The fresh-machine check (issue 18): the README's two commands on a Debian 12 machine that has
nothing of the project - no python3, compiler, cmake, chromium or venv (fresh_machine.py says
what the tree has and what of the host goes in) - as root, with a fresh HOME, from a checkout
under /tmp.

One module, steps in order, each a test that says what it proves:
1. apt reaches the registry from the tree (`apt-get update`);
2. `./lab test <a UI test> <the rt_core CMake tests>`: its set-up installs the system packages
   (apt) and makes the venv (pip); then chromium drives the dashboard and CMake/g++ build and
   run rt_core's unit tests, inside the tree;
3. `./lab serve` starts there without installing anything again; an upload of the base
   template builds (tests/xrf_testing/journey.py run with the tree's venv), the data folder
   being /var/lib/xrf-lab.

A step that cannot run is never passed: when the tree cannot reach apt's mirror, the system
packages come from this machine's apt cache and lists (offline) and the apt step is skipped
saying so; when pip's index cannot be reached, the venv step and everything after it are
skipped with pip's error. Needs root (debootstrap, mounts, pivot_root), as tests/deploy does.

The steps are run by fresh_run.py, a program that records what they did; the tests here assert on
that record. In a session with other tests the program starts with the session's first test, in
the background at low priority, and these tests run last (conftest.py, fresh_background.py).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from xrf_testing.fresh_background import BACKGROUND, Attached, Run
from xrf_testing.fresh_machine import Machine
from xrf_testing.fresh_run import CMAKE_TEST, JUNIT, UI_TEST, apt_packages
from xrf_testing.fresh_run import tail as _tail

pytestmark = pytest.mark.timeout(2400)


@dataclass
class Proc:
    returncode: int
    stdout: str
    stderr: str


@dataclass
class Fresh:
    """fresh_run.py's record (its Record), with the machine it made."""

    machine: Machine
    seconds: dict[str, float] = field(default_factory=dict)
    apt_missing: str = ""  # why setup_system's apt-get could not be exercised ("" = it was)
    no_python: str = ""  # why nothing after the system packages can run
    pip_missing: str = ""  # why setup_venv could not be exercised
    lab_test: Proc | None = None  # `./lab test ...`
    journey: dict | None = None
    journey_stderr: str = ""

    def skip_unless_venv(self) -> None:
        for why in (self.no_python, self.pip_missing):
            if why:
                pytest.skip(why)


@pytest.fixture(scope="module")
def fresh(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory):
    if os.geteuid() != 0:
        pytest.skip("the fresh-machine check needs root (debootstrap, mounts, pivot_root into the tree)")
    for tool in ("unshare", "pivot_root"):  # debootstrap is installed on demand (deploy_support)
        if shutil.which(tool) is None:
            pytest.skip(f"the fresh-machine check needs {tool} (util-linux)")
    background = request.config.stash.get(BACKGROUND, None)
    run = background.claim() if background else None
    if run is None and hasattr(request.config, "workerinput"):  # an xdist worker: the controller's run
        run = Attached.from_env()
    how = f"in the background since {run.seconds()} s" if run else "alone"
    if run is None:  # the check alone (or nothing else of the session got to run): as it always was
        run = Run(tmp_path_factory.mktemp("fresh-machine"), low_priority=False)
    seconds: dict[str, float] = {}
    try:
        run.hurry()  # the rest of the session is done: full priority from here
        rec = run.wait()
        seconds = rec.get("seconds", {})
        if rec.get("error"):
            pytest.fail(f"the fresh-machine run failed:\n{rec['error']}", pytrace=False)
        if rec["no_tree"]:
            pytest.skip(rec["no_tree"])
        lab = rec["lab_test"]
        yield Fresh(
            Machine(Path(rec["tree"]), rec["checkout"], Path(rec["work"])),
            seconds,
            rec["apt_missing"],
            rec["no_python"],
            rec["pip_missing"],
            Proc(**lab) if lab else None,
            rec["journey"],
            rec["journey_stderr"],
        )
    finally:
        print(f"fresh-machine check ({how}; {run.seconds()} s in all), seconds per step: {seconds}")
        run.close()


def _installed(tree: Path) -> set[str]:
    status = (tree / "var/lib/dpkg/status").read_text()
    return {m.group(1) for m in re.finditer(r"^Package: (\S+)\nStatus: install ok installed$", status, re.MULTILINE)}


def test_the_tree_starts_without_the_project(fresh: Fresh) -> None:
    """What makes the check mean something: before ./lab, none of what it installs was there
    (read from the cached tree, which ./lab never touches)."""
    from xrf_testing.deploy_support import ensure_debian_tree
    from xrf_testing.fresh_machine import PACKAGES

    pristine = _installed(ensure_debian_tree(PACKAGES))
    assert not {"python3", "cmake", "g++", "chromium", "build-essential"} & pristine
    assert "git" in pristine
    assert fresh.machine.checkout.startswith("/tmp/")


def test_setup_installs_the_system_packages(fresh: Fresh) -> None:
    if fresh.apt_missing:
        pytest.skip(fresh.apt_missing)
    out = fresh.lab_test.stderr
    assert "lab: installing system packages" in out, _tail(out)
    assert "no chromium could be installed" not in out, _tail(out)
    installed = _installed(fresh.machine.tree)
    missing = [p for p in [*apt_packages(), "chromium"] if p not in installed]
    assert not missing, missing
    for exe in ("usr/bin/cmake", "usr/bin/g++", "usr/bin/chromium", "usr/bin/python3"):
        assert (fresh.machine.tree / exe).exists(), exe


def test_setup_makes_the_venv_with_the_systems_python(fresh: Fresh) -> None:
    fresh.skip_unless_venv()
    out = fresh.lab_test.stderr
    assert "lab: installing the project into" in out, _tail(out)
    # apt's and pip's own output goes to the install log, not the terminal (issue 31: pip's warnings
    # buried the one-time password); pip runs without -q there, so its summary line is in the log.
    log = fresh.machine.tree / fresh.machine.checkout.lstrip("/") / ".cache/lab-install.log"
    assert "Successfully installed" not in out and "Successfully installed" in log.read_text(), _tail(out)
    venv = fresh.machine.tree / fresh.machine.checkout.lstrip("/") / ".venv"
    assert (venv / ".lab-stamp").exists(), _tail(out)
    assert "home = /usr/bin" in (venv / "pyvenv.cfg").read_text()
    assert (venv / "bin/xrf").exists()


def _junit_cases(fresh: Fresh) -> dict[str, str]:
    """test id -> passed/failed/skipped of the inner `./lab test` run."""
    path = fresh.machine.tree / JUNIT.lstrip("/")
    assert path.exists(), _tail(fresh.lab_test.stdout) + "\n" + _tail(fresh.lab_test.stderr)
    out = {}
    for case in ET.parse(path).getroot().iter("testcase"):
        verdict = "passed"
        for child in case:
            if child.tag in ("failure", "error", "skipped"):
                verdict = child.tag
        out[f"{case.get('classname')}::{case.get('name')}"] = verdict
    return out


@pytest.mark.parametrize("suite", [UI_TEST, CMAKE_TEST])
def test_the_installed_tools_run_the_tests(fresh: Fresh, suite: str) -> None:
    """chromium (the UI test) and CMake/g++ (rt_core's unit tests) as ./lab installed them: every
    test passes in the tree, none skipped."""
    fresh.skip_unless_venv()
    module = suite.removesuffix(".py").replace("/", ".")
    cases = {k: v for k, v in _junit_cases(fresh).items() if k.startswith(module)}
    assert cases, (suite, _tail(fresh.lab_test.stdout))
    assert set(cases.values()) == {"passed"}, (cases, _tail(fresh.lab_test.stdout, 6000))


def test_serve_starts_and_an_upload_builds(fresh: Fresh) -> None:
    """`./lab serve` as root from the /tmp checkout: the set-up is not repeated, the appliance
    keeps its data in /var/lib/xrf-lab, and the base template, uploaded, builds in the sandbox
    as the build user."""
    fresh.skip_unless_venv()
    j = fresh.journey
    assert j is not None, _tail(fresh.journey_stderr)
    assert j["ok"], json.dumps(j, indent=1)[-6000:]
    assert j["build"]["status"] == "ok"
    assert "/var/lib/xrf-lab" in j["modes"], j["modes"]
    assert not any(line.startswith("lab: installing") for line in j["lines"]), j["lines"][:10]
    assert any("/var/lib/xrf-lab" in line for line in j["lines"]), j["lines"][:20]
