"""Student projects build with xrflab.build, and the examples control the simulated robots.

Builds are slow-ish (a few seconds each), so every project is built once per session into a
session temp folder; the error-path tests copy a project and break the copy.
"""

from __future__ import annotations

import hashlib
import os
import re
import resource
import shutil
import subprocess
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from xrflab.build import BuildError, BuildResult, build_project
from xrflab.channels import lib

REPO = Path(__file__).resolve().parents[2]


PROJECTS = {
    "base": REPO / "student_projects/templates/base",
    "20sim": REPO / "student_projects/templates/20sim",
    "relbot": REPO / "student_projects/examples/relbot",
    "jiwy": REPO / "student_projects/examples/jiwy",
    "stage": REPO / "student_projects/examples/stage",
}
XRF2_FIXTURE_PARTS = REPO / "tests/fixtures/xrf2_project"
TWENTY_SIM_TEMPLATE = REPO / "student_projects/templates/20sim/controller"


def _xrf2_fixture(root: Path) -> Path:
    """The XRF2-layout fixture: its own files plus a 20-sim controller folder made from the
    template's, renamed to submodel PanTiltController with a 0.002 s step, so that the name and
    the step size can only come from the tokens file."""
    project = root / "xrf2_project"
    shutil.copytree(XRF2_FIXTURE_PARTS, project)
    controller = project / "controller"
    shutil.copytree(TWENTY_SIM_TEMPLATE, controller)
    for path in sorted(controller.rglob("*")):
        if not path.is_file():
            continue
        text = path.read_text().replace("LoopController", "PanTiltController")
        if path.name in ("LoopController.cpp", "LoopController.info", "LoopController_tokens.xml"):
            text = (
                text.replace("m_step_size = 0.001;", "m_step_size = 0.002;")
                .replace("Step size:   0.001", "Step size:   0.002")
                .replace("<![CDATA[0.001]]>", "<![CDATA[0.002]]>")
            )
        path.write_text(text)
        if "LoopController" in path.name:
            path.rename(path.with_name(path.name.replace("LoopController", "PanTiltController")))
    return project


def _quiet(_line: str) -> None:
    pass


@pytest.fixture(scope="session")
def build_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("project-builds")


_built: dict[str, BuildResult] = {}


def _build(name: str, build_root: Path) -> BuildResult:
    if name not in _built:
        _built[name] = build_project(PROJECTS[name], build_root / name, log=_quiet)
    return _built[name]


def _shm() -> str:
    return f"xrf-projtest-{os.getpid()}-{uuid.uuid4().hex[:8]}"


def _unlink_shm(name: str) -> None:
    try:
        (Path("/dev/shm") / name).unlink()
    except FileNotFoundError:
        pass


def _tree_digest(folder: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        h.update(str(p.relative_to(folder)).encode())
        if p.is_file():
            h.update(p.read_bytes())
    return h.hexdigest()


# ---------------------------------------------------------------------------------------
# builds


@pytest.mark.parametrize("name", list(PROJECTS))
def test_project_builds(name: str, build_root: Path) -> None:
    r = _build(name, build_root)
    assert r.layout == "xrf"
    assert r.executable.is_file() and os.access(r.executable, os.X_OK)
    assert "src/main.cpp" in r.taken


@pytest.mark.parametrize("name", list(PROJECTS))
def test_project_runs_cycles_in_simulation(name: str, build_root: Path, tmp_path: Path) -> None:
    """Each template and example, on the simulated RELbot and Jiwy: initialise, start, 500
    cycles in RUN without an error, then Ctrl-C ends it cleanly with PWM 0."""
    from xrflab.channels import Channels

    exe = _build(name, build_root).executable
    for sim in ("relbot", "jiwy"):
        shm = _shm()
        proc = subprocess.Popen(
            [str(exe)],
            cwd=tmp_path,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, "XRF_SHM": shm, "XRF_SIM": sim, "XRF_TRANSPORT": "sim", "XRF_PRIO": "0"},
        )
        try:
            ch = Channels.open(shm, wait_s=10)
            assert ch.wait_command(ch.send_command("initialise")).accepted
            deadline = time.monotonic() + 5
            while ch.status().state_name != "INITIALISED":
                assert time.monotonic() < deadline, ch.status()
                time.sleep(0.01)
            assert ch.wait_command(ch.send_command("start")).accepted
            start = ch.status().cycles
            while ch.status().cycles < start + 500:
                assert ch.status().state_name == "RUN", ch.status()
                time.sleep(0.01)
            proc.send_signal(2)
            out = proc.communicate(timeout=10)[0]
            assert proc.returncode == 0, out
            assert list(ch.shm.sim.pwm) == [0] * lib.XRF_MAX_CHANNELS
            ch.close()
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
            _unlink_shm(shm)


def test_20sim_template_reports_model(build_root: Path) -> None:
    r = _build("20sim", build_root)
    assert r.twenty_sim is not None
    assert r.twenty_sim["submodel"] == "LoopController"
    assert r.twenty_sim["time_step_size"] == "0.001"
    assert r.twenty_sim["frequency_hz"] == 1000
    assert "controller/LoopController.cpp" in r.taken
    assert "controller/common/xxinteg.cpp" in r.taken
    assert "own main()" in r.left_out["controller/test_LoopController.cpp"]


def test_20sim_template_runs_at_model_frequency(build_root: Path) -> None:
    """1 / TIME_STEP_SIZE (0.001 s), not anything derived from FINISH_TIME (10 s)."""
    r = _build("20sim", build_root)
    name = _shm()
    try:
        out = subprocess.run(
            [str(r.executable)],
            capture_output=True,
            text=True,
            timeout=30,
            cwd=r.build_dir,
            env={**os.environ, "XRF_MAX_CYCLES": "200", "XRF_SHM": name},
        )
    finally:
        _unlink_shm(name)
    text = out.stdout + out.stderr
    assert out.returncode == 0, text
    m = re.search(r"at (\d+) Hz", text)
    assert m, text
    assert int(m.group(1)) == 1000
    assert re.search(r"\b200 cycles\b", text), text


def test_editing_a_msg_regenerates_on_rebuild(tmp_path: Path) -> None:
    project = tmp_path / "base"
    shutil.copytree(PROJECTS["base"], project)
    build_project(project, tmp_path / "build", log=_quiet)
    with open(project / "msg/Xeno2Ros.msg", "a") as f:
        f.write("int32 extra_counter\n")
    build_project(project, tmp_path / "build", log=_quiet)
    headers = list((tmp_path / "build").rglob("xeno2_ros.hpp"))
    assert headers and "extra_counter" in headers[0].read_text()


def test_a_reused_build_folder_generates_with_this_rt_cores_generator(tmp_path: Path) -> None:
    """A build folder configured against an older rt_core once cached that install's msgdef.py
    (its headers would not match this runtime's layout); the next build must use this one's."""
    project = tmp_path / "base"
    shutil.copytree(PROJECTS["base"], project)
    build_project(project, tmp_path / "build", log=_quiet)
    stale = tmp_path / "old_msgdef.py"
    stale.write_text("# an older rt_core's generator: writes nothing\n")
    cache = tmp_path / "build" / "CMakeCache.txt"
    text = cache.read_text()
    assert "XRF_RT_MSGDEF:FILEPATH" not in text  # no longer cached
    cache.write_text(text + f"XRF_RT_MSGDEF:FILEPATH={stale}\n")  # as an older XrfRt left it
    with open(project / "msg/Xeno2Ros.msg", "a") as f:
        f.write("int32 extra_counter\n")
    build_project(project, tmp_path / "build", log=_quiet)
    headers = list((tmp_path / "build").rglob("xeno2_ros.hpp"))
    assert headers and "extra_counter" in headers[0].read_text()


# ---------------------------------------------------------------------------------------
# XRF2 layout


def test_xrf2_project_builds_unchanged(tmp_path: Path) -> None:
    fixture = _xrf2_fixture(tmp_path)
    before = _tree_digest(fixture)
    lines: list[str] = []
    r = build_project(fixture, tmp_path / "build", log=lines.append)
    assert _tree_digest(fixture) == before, "the project folder must not be written"
    assert r.layout == "xrf2"
    assert r.executable.is_file()
    for f in (
        "src/main.cpp",
        "src/ControlLoop.cpp",
        "include/ControlLoop.hpp",
        "controller/PanTiltController.cpp",
        "controller/common/xxmodel.h",
        "msg/Ros2Xeno.msg",
    ):
        assert f in r.taken, f
    assert "own main()" in r.left_out["controller/test_PanTiltController.cpp"]
    assert "XenoRosFramework" in r.left_out["CMakeLists.txt"]
    assert "package.xml" in r.left_out
    assert "scripts/get_tokens.py" in r.left_out
    # The submodel name is read from the tokens, not assumed to be LoopController.
    assert r.twenty_sim and r.twenty_sim["submodel"] == "PanTiltController"
    assert r.twenty_sim["frequency_hz"] == 500
    text = "\n".join(lines)
    assert "left out: controller/test_PanTiltController.cpp" in text


def test_xrf2_project_main_runs(tmp_path: Path) -> None:
    """The XRF2 main (evl_init, mlockall, SCHED_FIFO pthread on CPU 1) works on posix."""
    r = build_project(_xrf2_fixture(tmp_path), tmp_path / "build", log=_quiet)
    name = _shm()
    try:
        out = subprocess.run(
            [str(r.executable)],
            capture_output=True,
            text=True,
            timeout=30,
            cwd=tmp_path,
            env={**os.environ, "XRF_MAX_CYCLES": "100", "XRF_SHM": name},
        )
    finally:
        _unlink_shm(name)
    text = out.stdout + out.stderr
    assert out.returncode == 0, text
    assert "100 cycles" in text and "500 Hz" in text, text
    if os.geteuid() != 0 and resource.getrlimit(resource.RLIMIT_RTPRIO)[0] < 1:
        # A normal user: the SCHED_FIFO thread main asked for was started without it, and said so.
        assert "runs without real-time scheduling" in text, text


def test_xrf2_msg_dir_option(tmp_path: Path) -> None:
    """XRF2 projects often kept their messages in a separate package: msg_dir points there."""
    project = _xrf2_fixture(tmp_path)
    shutil.move(str(project / "msg"), str(tmp_path / "xrf2_msgs"))
    with pytest.raises(BuildError) as exc:
        build_project(project, tmp_path / "b1", log=_quiet)
    assert "msg" in str(exc.value)
    r = build_project(project, tmp_path / "b2", log=_quiet, msg_dir=tmp_path / "xrf2_msgs")
    assert r.executable.is_file()


# ---------------------------------------------------------------------------------------
# errors name the file


def test_missing_tokens_file(tmp_path: Path) -> None:
    project = tmp_path / "p"
    shutil.copytree(PROJECTS["20sim"], project)
    (project / "controller/LoopController_tokens.xml").unlink()
    with pytest.raises(BuildError) as exc:
        build_project(project, tmp_path / "build", log=_quiet)
    assert "_tokens.xml" in str(exc.value)
    assert str(project / "controller") in str(exc.value)


def test_tokens_without_time_step(tmp_path: Path) -> None:
    project = tmp_path / "p"
    shutil.copytree(PROJECTS["20sim"], project)
    tokens = project / "controller/LoopController_tokens.xml"
    # Keep FINISH_TIME and a near-miss name: neither may be taken for the step size.
    text = tokens.read_text().replace('name="TIME_STEP_SIZE"', 'name="OLD_TIME_STEP_SIZE"')
    tokens.write_text(text)
    with pytest.raises(BuildError) as exc:
        build_project(project, tmp_path / "build", log=_quiet)
    assert "LoopController_tokens.xml" in str(exc.value)
    assert "TIME_STEP_SIZE" in str(exc.value)


def test_bad_msg_names_file_and_line(tmp_path: Path) -> None:
    project = tmp_path / "p"
    shutil.copytree(PROJECTS["base"], project)
    (project / "msg/Ros2Xeno.msg").write_text("float64 steer_left\nfloat64 steer right x\n")
    with pytest.raises(BuildError) as exc:
        build_project(project, tmp_path / "build", log=_quiet)
    assert re.search(r"Ros2Xeno\.msg:2\b", str(exc.value)), str(exc.value)


def test_missing_msg_folder(tmp_path: Path) -> None:
    project = tmp_path / "p"
    shutil.copytree(PROJECTS["base"], project)
    shutil.rmtree(project / "msg")
    with pytest.raises(BuildError) as exc:
        build_project(project, tmp_path / "build", log=_quiet)
    assert str(project / "msg") in str(exc.value)


def test_missing_msg_file(tmp_path: Path) -> None:
    project = tmp_path / "p"
    shutil.copytree(PROJECTS["base"], project)
    (project / "msg/Xeno2Ros.msg").unlink()
    with pytest.raises(BuildError) as exc:
        build_project(project, tmp_path / "build", log=_quiet)
    assert "Xeno2Ros.msg" in str(exc.value)


# ---------------------------------------------------------------------------------------
# closed loop on the simulated robots


class _Running:
    def __init__(self, exe: Path, sim: str, cwd: Path) -> None:
        from xrflab.channels import Channels

        self.name = _shm()
        env = {**os.environ, "XRF_SIM": sim, "XRF_SHM": self.name, "XRF_TRANSPORT": "sim", "XRF_MAX_CYCLES": "30000"}
        self.proc = subprocess.Popen(
            [str(exe)], cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        )
        try:
            self.ch = Channels.open(self.name, wait_s=10.0)
        except Exception:
            self.stop()
            raise

    def command(self, cmd: str) -> None:
        res = self.ch.wait_command(self.ch.send_command(cmd), timeout=3.0)
        assert res.accepted, f"{cmd}: {res.reason}"

    def wait_state(self, state: str, timeout: float = 3.0) -> None:
        # A state hook may take several cycles (the examples zero the encoders one cycle
        # after initialising the board), so wait for the state rather than assume it.
        deadline = time.monotonic() + timeout
        while self.ch.status().state_name != state:
            assert time.monotonic() < deadline, f"not {state}: {self.ch.status().state_name}"
            time.sleep(0.005)

    def stop(self) -> str:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        out = self.proc.stdout.read() if self.proc.stdout else ""
        if getattr(self, "ch", None) is not None:
            self.ch.close()
        _unlink_shm(self.name)
        return out


@pytest.fixture
def run_example(build_root: Path) -> Iterator:
    started: list[_Running] = []

    def start(name: str, sim: str) -> _Running:
        r = _build(name, build_root)
        run = _Running(r.executable, sim, r.build_dir)
        started.append(run)
        return run

    yield start
    for run in started:
        run.stop()


def _converge(run: _Running, targets: dict[str, float], tol: float, within_s: float) -> dict:
    """Wait until every Xeno2Ros field is within tol of its target; return the last values."""
    reader = run.ch.telemetry_reader()
    deadline = time.monotonic() + within_s
    last: dict = {}
    while time.monotonic() < deadline:
        for t in reader.read():
            if t.xeno2ros:
                last = t.xeno2ros
        if last and all(abs(last[k] - v) < tol for k, v in targets.items()):
            # Stay there, not just pass through: check again a little later.
            time.sleep(0.3)
            for t in reader.read():
                if t.xeno2ros:
                    last = t.xeno2ros
            if all(abs(last[k] - v) < tol for k, v in targets.items()):
                return last
        time.sleep(0.02)
    raise AssertionError(f"no convergence to {targets} within {within_s} s: last {last}")


def test_relbot_reaches_wheel_positions(run_example) -> None:
    run = run_example("relbot", "relbot")
    run.command("initialise")
    run.wait_state("INITIALISED")
    run.command("start")
    targets = {"pos_left": 3.0, "pos_right": -2.0}
    run.ch.write_ros2xeno({"steer_left": 3.0, "steer_right": -2.0})
    _converge(run, targets, tol=0.05, within_s=6.0)
    run.command("stop")


def test_jiwy_reaches_camera_angles(run_example) -> None:
    run = run_example("jiwy", "jiwy")
    run.command("initialise")
    run.wait_state("INITIALISED")
    run.command("start")
    targets = {"pan": 0.5, "tilt": -0.3}
    run.ch.write_ros2xeno({"pan_setpoint": 0.5, "tilt_setpoint": -0.3})
    _converge(run, targets, tol=0.01, within_s=6.0)
    run.command("stop")


def test_stage_reaches_its_position(run_example) -> None:
    """The third plant (issue 20): the stage example on the simulated linear stage moves the
    carriage 50 mm out and 30 mm back past its start, each time staying within 0.5 mm."""
    run = run_example("stage", "stage")
    run.command("initialise")
    run.wait_state("INITIALISED")
    run.command("start")
    run.ch.write_ros2xeno({"position_setpoint": 0.05})
    _converge(run, {"position": 0.05}, tol=0.0005, within_s=6.0)
    run.ch.write_ros2xeno({"position_setpoint": -0.03})
    _converge(run, {"position": -0.03}, tol=0.0005, within_s=6.0)
    # The plant itself (the board's mirror, not the controller's counting) is there too.
    assert abs(run.ch.shm.sim.plant[0] - (-0.03)) < 0.0005
    run.command("stop")
