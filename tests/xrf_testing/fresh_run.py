"""The fresh-machine check's steps, run as a program that records what happened as JSON
(test_fresh_machine.py asserts on that record; fresh_background.py runs this program, in the
background while the rest of the suite runs, or in the foreground when the check runs alone).

    python fresh_run.py DEST RESULT.json

In order: a copy of the fresh tree under DEST (fresh_machine.make_machine); `apt-get update`
(else the system packages from this machine's apt cache, offline); `./lab test <a UI test> <the
rt_core CMake tests>`; a probe of pip's index when no venv was made; `./lab serve` + an upload
that builds (tests/xrf_testing/journey.py). A step that cannot run records why, and what it
prevents is not run. DEST is left for the tests to read (the tree, its venv, the JUnit file); its
owner removes it.

A program, not a thread of pytest, so that one process tree holds everything the check starts and
can be killed as a whole (fresh_background.py).
"""

from __future__ import annotations

import configparser
import json
import os
import re
import shutil
import socket
import sys
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path

if __name__ == "__main__":
    # Run as a program (fresh_background.py starts it by path, outside pytest): tests/ is put on
    # the path so its helpers import as `xrf_testing` here as they do in the tests.
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from xrf_testing.deploy_support import REPO  # noqa: E402
from xrf_testing.fresh_machine import Machine, _user_pip_conf, make_machine  # noqa: E402

UI_TEST = "tests/ui/test_system_ui.py"  # the quickest browser test: needs chromium and serve
CMAKE_TEST = "tests/rt_core/test_ctest.py"  # CMake + g++ build rt_core's unit tests, then runs them
JUNIT = "/tmp/fresh-machine-junit.xml"  # in the tree, outside the checkout


def apt_packages() -> list[str]:
    """APT_PACKAGES as ./lab lists them (chromium is installed apart)."""
    text = (REPO / "lab").read_text()
    words: list[str] = []
    for m in re.finditer(r"^APT_PACKAGES\+?=\(([^)]*)\)", text, re.MULTILINE):
        words += m.group(1).split()
    return words


def pip_index() -> str:
    """The index pip uses here (PyPI unless the configuration says otherwise)."""
    url = os.environ.get("PIP_INDEX_URL", "")
    for conf in (Path("/etc/pip.conf"), Path("/etc/xdg/pip/pip.conf"), _user_pip_conf()):
        if not url and conf and conf.exists():
            cp = configparser.ConfigParser()
            cp.read(conf)
            url = cp.get("global", "index-url", fallback="")
    return (url or "https://pypi.org/simple").rstrip("/")


def tail(text: str, n: int = 3000) -> str:
    return text[-n:].strip()


@dataclass
class Record:
    """What the steps did; every field JSON."""

    no_tree: str = ""  # why there is no machine at all ("" = there is)
    tree: str = ""
    checkout: str = ""
    work: str = ""
    seconds: dict[str, float] = field(default_factory=dict)
    apt_missing: str = ""  # why setup_system's apt-get could not be exercised ("" = it was)
    no_python: str = ""  # why nothing after the system packages can run
    pip_missing: str = ""  # why setup_venv could not be exercised
    lab_test: dict | None = None  # returncode, stdout, stderr of `./lab test ...`
    journey: dict | None = None
    journey_stderr: str = ""
    error: str = ""  # the program's own traceback, if it failed (the tests fail with it)


def _timed(rec: Record, machine: Machine, name: str, command: list[str], timeout: float):
    t = time.monotonic()
    proc = machine.enter(command, timeout)
    rec.seconds[name] = round(time.monotonic() - t, 1)
    return proc


def _offline_packages(rec: Record, machine: Machine) -> str:
    """No mirror: the system packages from this machine's apt lists and archive cache, so that the
    steps after apt can still run. Returns why even that failed ("" if it worked)."""
    lists = machine.tree / "var/lib/apt/lists"
    for p in Path("/var/lib/apt/lists").glob("*_Packages*"):
        shutil.copy2(p, lists / p.name)
    proc = _timed(
        rec,
        machine,
        "apt offline",
        ["apt-get", "install", "-y", "-q", "--no-download", "--no-install-recommends", *apt_packages(), "chromium"],
        1200,
    )
    if proc.returncode != 0:
        return f"apt-get install --no-download from this machine's cache failed:\n{tail(proc.stdout + proc.stderr)}"
    return ""


def _free_port() -> int:
    # The tree shares this machine's network namespace (the registries), so its port must be free here.
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run(dest: Path, rec: Record) -> None:
    t = time.monotonic()
    try:
        machine = make_machine(dest)
    except RuntimeError as exc:  # debootstrap could not reach its mirror: there is no machine at all
        rec.no_tree = f"no step exercised: the fresh Debian tree could not be made: {exc}"
        return
    rec.tree, rec.checkout, rec.work = str(machine.tree), machine.checkout, str(machine.work)
    rec.seconds["tree"] = round(time.monotonic() - t, 1)
    probe = _timed(rec, machine, "apt probe", ["apt-get", "update", "-q"], 600)
    if probe.returncode != 0:
        rec.apt_missing = (
            "./lab's setup_system (apt-get update/install) NOT exercised: the tree cannot reach "
            f"apt's mirror:\n{tail(probe.stdout + probe.stderr)}"
        )
        rec.no_python = _offline_packages(rec, machine)
    if not rec.no_python:
        lab = _timed(rec, machine, "lab test", ["./lab", "test", UI_TEST, CMAKE_TEST, f"--junitxml={JUNIT}"], 2000)
        rec.lab_test = {"returncode": lab.returncode, "stdout": lab.stdout, "stderr": lab.stderr}
        if not (machine.tree / machine.checkout.lstrip("/") / ".venv/.lab-stamp").exists():
            # Only now is there a python3 in the tree to ask pip's index with; reachable, the
            # failure is ./lab's and the tests fail on it.
            index = pip_index()
            pip = _timed(
                rec,
                machine,
                "pip probe",
                [
                    "python3",
                    "-c",
                    "import sys, urllib.request; urllib.request.urlopen(sys.argv[1] + '/pip/', timeout=30)",
                    index,
                ],
                120,
            )
            if pip.returncode != 0:
                rec.pip_missing = (
                    f"./lab's setup_venv (pip install) and every step after it NOT exercised: the "
                    f"tree cannot reach pip's index {index}:\n{tail(pip.stderr, 800)}"
                )
    if not rec.no_python and not rec.pip_missing:
        port = _free_port()
        j = _timed(
            rec,
            machine,
            "journey",
            [
                ".venv/bin/python",
                "tests/xrf_testing/journey.py",
                "--port",
                str(port),
                "--mode",
                "/var/lib/xrf-lab",
                "--",
                "./lab",
                "serve",
                "--port",
                str(port),
            ],
            900,
        )
        lines = j.stdout.strip().splitlines()
        rec.journey = json.loads(lines[-1]) if lines and lines[-1].startswith("{") else None
        rec.journey_stderr = j.stdout + j.stderr


def main(argv: list[str]) -> int:
    dest, result = Path(argv[1]), Path(argv[2])
    rec = Record()
    try:
        run(dest, rec)
    except Exception:  # noqa: BLE001 - the program's boundary: whatever stopped it, the tests say
        rec.error = traceback.format_exc()
    result.write_text(json.dumps(asdict(rec)))
    return 1 if rec.error else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
