"""XRF2's student API, both releases, as a contract: small translation units written here
(tests/rt_core/xrf2_api/{common,v1_0,v1_1}) use every name the contract in docs/students/xrf2-api.md
lists, are compiled against rt_core's installed package (find_package(XrfRt) +
xrf_add_controller, as a student project is), and run on the simulated RELbot: driven to RUN,
they check what the members hold and print "surface: N failed"."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from xrf_testing.loops import LoopProcess
from xrflab.build import _xrfrt_config_dir, ensure_rt_core

REPO = Path(__file__).resolve().parents[3]
HERE = Path(__file__).resolve().parent
CONTRACT = REPO / "docs/students/xrf2-api.md"
TWENTY_SIM = REPO / "student_projects/templates/20sim/controller"
RELEASES = ("v1.0", "v1.1")


def contract(release: str) -> list[tuple[str, str]]:
    """(kind, name) for every entry of the contract's ```xrf2-surface``` blocks that apply to
    `release` (blocks tagged `both` or the release)."""
    text = CONTRACT.read_text()
    out = []
    for tag, body in re.findall(r"```xrf2-surface ([\w.]+)\n(.*?)```", text, re.S):
        if tag in ("both", release):
            for line in body.splitlines():
                line = line.split("#", 1)[0].strip()
                if line:
                    kind, name = line.split(None, 1)
                    out.append((kind, name.strip()))
    return out


def surface_sources(release: str) -> list[Path]:
    return sorted((HERE / "common").glob("*.cpp")) + sorted((HERE / release.replace(".", "_")).glob("*.cpp"))


@pytest.mark.parametrize("release", RELEASES)
def test_every_contract_name_is_used_by_the_surface(release: str) -> None:
    entries = contract(release)
    assert len(entries) > 80, f"the contract for {release} lists {len(entries)} names"
    text = "\n".join(p.read_text() for p in surface_sources(release))
    missing = []
    for kind, name in entries:
        if kind == "header":
            found = f'#include "{name}"' in text or f"#include <{name}>" in text
        elif kind == "absent":
            continue
        else:
            found = re.search(rf"(?<!\w){re.escape(name)}\b", text) is not None
        if not found:
            missing.append(f"{kind} {name}")
    assert not missing, f"{release}: contract names no surface file uses: {missing}"
    # The other release's message names are not what this release's controller uses.
    for kind, name in entries:
        if kind == "absent":
            own = (HERE / release.replace(".", "_") / "surface_rosico.cpp").read_text()
            assert not re.search(rf"\b{name}\b", own), f"{release} surface uses {name}"


def _build_surface(release: str, work: Path) -> Path:
    prefix = ensure_rt_core(log=lambda line: None)
    rel = release.replace(".", "_")
    srcs = " ".join(f'"{p}"' for p in surface_sources(release))
    (work / "CMakeLists.txt").write_text(
        "cmake_minimum_required(VERSION 3.16)\n"
        f"project(surface_{rel} LANGUAGES C CXX)\n"
        "find_package(XrfRt REQUIRED)\n"
        f"xrf_add_controller(surface_{rel} SOURCES {srcs}\n"
        f'  INCLUDE_DIRS "{HERE / "common"}" MSG_DIR "{HERE / "msg"}" TWENTY_SIM "{TWENTY_SIM}")\n'
    )
    build = work / "build"
    cfg = subprocess.run(
        [
            "cmake",
            "-S",
            str(work),
            "-B",
            str(build),
            f"-DCMAKE_PREFIX_PATH={prefix}",
            f"-DXrfRt_DIR={_xrfrt_config_dir(prefix)}",
            f"-DPython3_EXECUTABLE={sys.executable}",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert cfg.returncode == 0, cfg.stdout[-3000:] + cfg.stderr[-3000:]
    b = subprocess.run(["cmake", "--build", str(build), "-j2"], capture_output=True, text=True, timeout=600)
    assert b.returncode == 0, b.stdout[-6000:] + b.stderr[-3000:]
    return build / f"surface_{rel}"


@pytest.mark.parametrize("release", RELEASES)
def test_surface_compiles_against_the_installed_package_and_runs(release: str, tmp_path: Path, shm_name: str) -> None:
    exe = _build_surface(release, tmp_path)
    lp = LoopProcess(exe, shm_name, tmp_path, XRF_SIM="relbot", XRF_TRANSPORT="sim", XRF_PRIO="0", XRF_QUIET="0")
    try:
        assert lp.ch.info["cycle_freq"] == 500
        lp.command("initialise", "RUN")  # initialised() returns 1: straight on to RUN
        lp.ch.write_ros2xeno({"setpoint": 1.5, "counter": 41})
        reader = lp.ch.telemetry_reader()
        lp.wait_cycles(300)
        latest = reader.read()[-1]
        # Written through the release's names, published from the same object.
        assert latest.xeno2ros["counter"] == 42 and latest.xeno2ros["state"] == 4, latest
        # position = setpoint (1.5, read through the release's name) + an encoder count (a whole
        # number from the hook's cycle, a cycle older than the sample's own enc).
        assert latest.xeno2ros["position"] % 1 == 0.5 and 1.5 <= latest.xeno2ros["position"] < 16385.5, latest
        # actuate_data.pwm1 = MAX_PWM_VALUE (409) reaches the board as 409.
        assert lp.ch.shm.sim.pwm[0] == 409
        lp.command("stop", "STOPPED")
        lp.command("quit")
        rc, out = lp.finish()
    finally:
        lp.stop()
    assert "surface: headers checked" in out, out
    assert "surface: 0 failed" in out and rc == 0, out
