"""The runtime library a student controller links carries no self-check: the checker is the
xrf-selfcheck tool of its own (rt_core/tools/selfcheck), linked against the library for the
board's transports, never the other way round."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from xrflab.build import ensure_rt_core


def symbols(path: Path) -> list[str]:
    res = subprocess.run(["nm", "--defined-only", str(path)], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    return [line.split()[-1] for line in res.stdout.splitlines() if len(line.split()) >= 2]


@pytest.fixture(scope="module")
def prefix() -> Path:
    return Path(ensure_rt_core(log=lambda line: None))


def test_installed_runtime_library_has_no_selfcheck_code(prefix: Path) -> None:
    libs = sorted(prefix.glob("lib*/libxrf_rt.a"))
    assert len(libs) == 1, libs
    names = symbols(libs[0])
    assert "xrf_ico_pwm_max" in names  # the symbols were read
    assert [n for n in names if "selfcheck" in n.lower()] == []
    members = subprocess.run(["ar", "t", str(libs[0])], capture_output=True, text=True, timeout=60).stdout.split()
    assert members and not [m for m in members if "selfcheck" in m or "profile_flat" in m], members


def test_controller_built_against_it_has_no_selfcheck_code(probe_exe: Path) -> None:
    names = symbols(probe_exe)
    assert any(n.startswith("xrf_") for n in names)
    assert [n for n in names if "selfcheck" in n.lower()] == []


def test_the_selfcheck_tool_has_it(prefix: Path) -> None:
    tool = prefix / "bin" / "xrf-selfcheck"
    names = symbols(tool)
    assert {"xrf_selfcheck_run", "xrf_selfcheck_profile_read"} <= set(names)
