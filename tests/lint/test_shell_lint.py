"""The shell scripts people and CI run (./lab, .ci/run, deploy/): shellcheck finds nothing, and
no pipeline feeds `grep -q` (under `set -o pipefail` grep's early exit fails the writer with
SIGPIPE, so a match reads as a miss: ./lab once never installed chromium that way).

Which scripts are linted is said once, by `./lab check --list shell`; this file asks it."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def shell_scripts() -> list[Path]:
    proc = subprocess.run(
        [str(REPO / "lab"), "check", "--list", "shell"], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    return [REPO / line for line in proc.stdout.splitlines() if line]


def test_the_linted_set_covers_the_installers() -> None:
    names = {p.relative_to(REPO).as_posix() for p in shell_scripts()}
    assert {"lab", ".ci/run", "deploy/install", "deploy/uninstall"} <= names


def test_shellcheck_finds_nothing() -> None:
    proc = subprocess.run([str(REPO / "lab"), "check", "shell"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f"shellcheck findings:\n{proc.stdout}{proc.stderr}"


PIPE_INTO_QUIET_GREP = re.compile(r"\|\s*grep\s+(-\w*q|--quiet|--silent)")


@pytest.mark.parametrize("script", shell_scripts(), ids=lambda p: p.relative_to(REPO).as_posix())
def test_no_pipeline_ends_in_grep_q(script: Path) -> None:
    hits = [
        f"{script.name}:{n}: {line.strip()}"
        for n, line in enumerate(script.read_text().splitlines(), 1)
        if PIPE_INTO_QUIET_GREP.search(line) and not line.lstrip().startswith("#")
    ]
    assert not hits, "a pipeline into grep -q fails with SIGPIPE under pipefail:\n" + "\n".join(hits)


def _lab_function(name: str) -> str:
    text = (REPO / "lab").read_text()
    m = re.search(rf"^{name}\(\) {{\n.*?^}}\n", text, re.MULTILINE | re.DOTALL)
    assert m, f"no function {name} in ./lab"
    return m.group(0)


def test_chromium_package_finds_the_candidate_every_time() -> None:
    """With the real apt-cache, as ./lab runs it (set -euo pipefail): the answer is the same on
    each of 20 tries (the pipe into grep -q answered "none" about 4 times in 5)."""
    if shutil.which("apt-cache") is None:
        pytest.skip("no apt-cache: not a Debian/Ubuntu system, ./lab does not install chromium here")
    policy = subprocess.run(
        ["apt-cache", "policy", "chromium", "chromium-browser"], capture_output=True, text=True, timeout=60
    ).stdout
    candidates = re.findall(r"^(\S+):\n(?:.*\n)*?\s+Candidate: (?!\(none\))", policy, re.MULTILINE)
    if not candidates:
        pytest.skip("apt has no candidate for chromium or chromium-browser here (apt-get update not run?)")
    script = (
        "set -euo pipefail\n"
        + _lab_function("chromium_package")
        + ("for i in $(seq 20); do chromium_package || echo none; done\n")
    )
    out = subprocess.run(["bash", "-c", script], capture_output=True, text=True, timeout=300).stdout.split()
    assert out == [candidates[0]] * 20


def test_missing_apt_packages_names_only_the_missing() -> None:
    if shutil.which("dpkg-query") is None:
        pytest.skip("no dpkg-query: not a Debian/Ubuntu system")
    script = (
        "set -euo pipefail\n"
        + _lab_function("missing_apt_packages")
        + ("missing_apt_packages bash xrf-no-such-package-1 coreutils xrf-no-such-package-2\n")
    )
    out = subprocess.run(["bash", "-c", script], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["xrf-no-such-package-1", "xrf-no-such-package-2"]
