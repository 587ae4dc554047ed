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
"""

from __future__ import annotations

import configparser
import json
import os
import re
import shutil
import socket
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from deploy_support import REPO
from fresh_machine import Machine, _user_pip_conf, make_machine

pytestmark = pytest.mark.timeout(2400)

UI_TEST = "tests/ui/test_system_ui.py"       # the quickest browser test: needs chromium and serve
CMAKE_TEST = "tests/rt_core/test_ctest.py"  # CMake + g++ build rt_core's unit tests, then runs them
JUNIT = "/tmp/fresh-machine-junit.xml"      # in the tree, outside the checkout


def _apt_packages() -> list[str]:
    """APT_PACKAGES as ./lab lists them (chromium is installed apart)."""
    text = (REPO / "lab").read_text()
    words: list[str] = []
    for m in re.finditer(r"^APT_PACKAGES\+?=\(([^)]*)\)", text, re.MULTILINE):
        words += m.group(1).split()
    return words


def _pip_index() -> str:
    """The index pip uses here (PyPI unless the configuration says otherwise)."""
    url = os.environ.get("PIP_INDEX_URL", "")
    for conf in (Path("/etc/pip.conf"), Path("/etc/xdg/pip/pip.conf"), _user_pip_conf()):
        if not url and conf and conf.exists():
            cp = configparser.ConfigParser()
            cp.read(conf)
            url = cp.get("global", "index-url", fallback="")
    return (url or "https://pypi.org/simple").rstrip("/")


def _tail(text: str, n: int = 3000) -> str:
    return text[-n:].strip()


@dataclass
class Fresh:
    machine: Machine
    seconds: dict[str, float] = field(default_factory=dict)
    apt_missing: str = ""     # why setup_system's apt-get could not be exercised ("" = it was)
    no_python: str = ""       # why nothing after the system packages can run
    pip_missing: str = ""     # why setup_venv could not be exercised
    lab_test: object = None   # CompletedProcess of `./lab test ...`
    journey: dict | None = None
    journey_stderr: str = ""

    def skip_unless_venv(self) -> None:
        for why in (self.no_python, self.pip_missing):
            if why:
                pytest.skip(why)


def _timed(fresh: Fresh, name: str, command: list[str], timeout: float):
    t = time.monotonic()
    proc = fresh.machine.enter(command, timeout)
    fresh.seconds[name] = round(time.monotonic() - t, 1)
    return proc


def _offline_packages(fresh: Fresh) -> str:
    """No mirror: the system packages from this machine's apt lists and archive cache, so that the
    steps after apt can still run. Returns why even that failed ("" if it worked)."""
    lists = fresh.machine.tree / "var/lib/apt/lists"
    for p in Path("/var/lib/apt/lists").glob("*_Packages*"):
        shutil.copy2(p, lists / p.name)
    proc = _timed(fresh, "apt offline", ["apt-get", "install", "-y", "-q", "--no-download", "--no-install-recommends",
                                         *_apt_packages(), "chromium"], 1200)
    if proc.returncode != 0:
        return f"apt-get install --no-download from this machine's cache failed:\n{_tail(proc.stdout + proc.stderr)}"
    return ""


@pytest.fixture(scope="module")
def fresh(tmp_path_factory: pytest.TempPathFactory):
    if os.geteuid() != 0:
        pytest.skip("the fresh-machine check needs root (debootstrap, mounts, pivot_root into the tree)")
    for tool in ("unshare", "pivot_root"):  # debootstrap is installed on demand (deploy_support)
        if shutil.which(tool) is None:
            pytest.skip(f"the fresh-machine check needs {tool} (util-linux)")
    dest = tmp_path_factory.mktemp("fresh-machine")
    t = time.monotonic()
    try:
        machine = make_machine(dest)
    except RuntimeError as exc:  # debootstrap could not reach its mirror: there is no machine at all
        shutil.rmtree(dest, ignore_errors=True)
        pytest.skip(f"no step exercised: the fresh Debian tree could not be made: {exc}")
    f = Fresh(machine)
    f.seconds["tree"] = round(time.monotonic() - t, 1)
    try:
        probe = _timed(f, "apt probe", ["apt-get", "update", "-q"], 600)
        if probe.returncode != 0:
            f.apt_missing = ("./lab's setup_system (apt-get update/install) NOT exercised: the tree cannot reach "
                             f"apt's mirror:\n{_tail(probe.stdout + probe.stderr)}")
            f.no_python = _offline_packages(f)
        if not f.no_python:
            f.lab_test = _timed(f, "lab test", ["./lab", "test", UI_TEST, CMAKE_TEST, f"--junitxml={JUNIT}"], 2000)
            if not (machine.tree / machine.checkout.lstrip("/") / ".venv/.lab-stamp").exists():
                # Only now is there a python3 in the tree to ask pip's index with; reachable, the
                # failure is ./lab's and the tests below fail on it.
                index = _pip_index()
                pip = _timed(f, "pip probe", ["python3", "-c", "import sys, urllib.request; "
                                              "urllib.request.urlopen(sys.argv[1] + '/pip/', timeout=30)", index], 120)
                if pip.returncode != 0:
                    f.pip_missing = (f"./lab's setup_venv (pip install) and every step after it NOT exercised: the "
                                     f"tree cannot reach pip's index {index}:\n{_tail(pip.stderr, 800)}")
        if not f.no_python and not f.pip_missing:
            port = _free_port()
            j = _timed(f, "journey", [".venv/bin/python", "tests/xrf_testing/journey.py", "--port", str(port),
                                      "--mode", "/var/lib/xrf-lab", "--", "./lab", "serve", "--port", str(port)], 900)
            lines = j.stdout.strip().splitlines()
            f.journey = json.loads(lines[-1]) if lines and lines[-1].startswith("{") else None
            f.journey_stderr = j.stdout + j.stderr
        yield f
    finally:
        print(f"fresh-machine check, seconds per step: {f.seconds}")
        shutil.rmtree(dest, ignore_errors=True)  # about 2 GB after the set-up


def _free_port() -> int:
    # The tree shares this machine's network namespace (the registries), so its port must be free here.
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _installed(tree: Path) -> set[str]:
    status = (tree / "var/lib/dpkg/status").read_text()
    return {m.group(1) for m in re.finditer(r"^Package: (\S+)\nStatus: install ok installed$", status, re.MULTILINE)}


def test_the_tree_starts_without_the_project(fresh: Fresh) -> None:
    """What makes the check mean something: before ./lab, none of what it installs was there
    (read from the cached tree, which ./lab never touches)."""
    from deploy_support import ensure_debian_tree
    from fresh_machine import PACKAGES
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
    missing = [p for p in [*_apt_packages(), "chromium"] if p not in installed]
    assert not missing, missing
    for exe in ("usr/bin/cmake", "usr/bin/g++", "usr/bin/chromium", "usr/bin/python3"):
        assert (fresh.machine.tree / exe).exists(), exe


def test_setup_makes_the_venv_with_the_systems_python(fresh: Fresh) -> None:
    fresh.skip_unless_venv()
    out = fresh.lab_test.stderr
    assert "lab: installing the project into" in out, _tail(out)
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
