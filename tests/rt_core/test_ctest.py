"""The C/C++ unit tests of rt_core (rt_core/tests/test_*.c|cpp), built with CMake and run one by
one so each shows up, and fails, on its own."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
UNIT_TESTS = sorted(p.stem for p in (REPO / "rt_core/tests").glob("test_*.c*"))


@pytest.fixture(scope="session")
def unit_build(tmp_path_factory: pytest.TempPathFactory) -> Path:
    build = tmp_path_factory.mktemp("rt_core-tests")
    subprocess.run(
        [
            "cmake",
            "-S",
            str(REPO / "rt_core"),
            "-B",
            str(build),
            "-DXRF_BUILD_TESTS=ON",
            "-DCMAKE_BUILD_TYPE=RelWithDebInfo",
        ],
        check=True,
        capture_output=True,
    )
    r = subprocess.run(["cmake", "--build", str(build), "-j2"], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-4000:]
    return build


@pytest.mark.parametrize("name", UNIT_TESTS)
def test_unit(unit_build: Path, name: str) -> None:
    r = subprocess.run([str(unit_build / name)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, f"{name} failed:\n{r.stdout[-6000:]}\n{r.stderr[-3000:]}"
    assert " 0 failed" in r.stdout, r.stdout[-2000:]
