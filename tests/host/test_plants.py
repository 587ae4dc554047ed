"""One list of simulated plants: rt_core's plant table (rt_core/src/plants.c). Python reads it
through the cffi binding (xrflab.plants); the CLI, the request models and the 3D view's counter
range derive from it, so a plant added to the table needs no edit here or there."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from pydantic import ValidationError

from xrflab import cli, plants
from xrflab.channels import lib
from xrflab.server.http.projects import RunBuild
from xrflab.server.http.runs import StartRun
from xrflab.viz import kinematics

RT_SRC = Path(__file__).resolve().parents[2] / "rt_core" / "src"


def table_rows() -> list[str]:
    """The rows of XRF_PLANT_TABLE in plants.c, read from the source itself."""
    text = (RT_SRC / "plants.c").read_text()
    block = re.search(r"#define XRF_PLANT_TABLE\(ROW\)(.*?)\n\n", text, re.S)
    assert block, "plants.c has no XRF_PLANT_TABLE"
    return re.findall(r"ROW\((\w+)\)", block.group(1))


def test_python_reads_the_c_table_in_order() -> None:
    rows = table_rows()
    assert rows[:2] == ["relbot", "jiwy"]  # ids 1 and 2 are XRF_SIM_RELBOT, XRF_SIM_JIWY
    assert list(plants.names()) == rows
    assert [p.id for p in plants.plants()] == list(range(1, len(rows) + 1))


def test_every_plant_file_is_a_row_and_every_row_has_its_file() -> None:
    defined = {}
    for path in RT_SRC.glob("plant_*.c"):
        m = re.search(r"const struct xrf_plant_ops xrf_plant_(\w+) = \{.*?\.name = \"(\w+)\"", path.read_text(), re.S)
        assert m, f"{path.name} defines no xrf_plant_<name> row"
        assert m.group(1) == m.group(2) == path.stem.removeprefix("plant_"), path.name
        defined[m.group(1)] = path
    assert sorted(defined) == sorted(table_rows())


def test_rows_describe_their_plant() -> None:
    relbot, jiwy = plants.get("relbot"), plants.get("jiwy")
    assert relbot.axes == 2 and relbot.state[:3] == ("x m", "y m", "theta rad")
    assert jiwy.axes == 2 and jiwy.state[:2] == ("pan rad", "tilt rad")
    for p in plants.plants():
        assert p.title and 1 <= p.axes <= 12 and 1 <= len(p.state) <= 8
    with pytest.raises(KeyError, match="have: relbot, jiwy"):
        plants.get("warthog")


def test_cli_sim_takes_the_table() -> None:
    parser = cli.build_parser()
    for name in plants.names():
        assert parser.parse_args(["run", "build/x", "--sim", name]).sim == name
    with pytest.raises(SystemExit) as exc:
        parser.parse_args(["run", "build/x", "--sim", "warthog"])
    assert exc.value.code == 2


@pytest.mark.parametrize("model", [StartRun, RunBuild])
def test_run_requests_take_the_table(model) -> None:
    kw = {"build": "x"} if model is StartRun else {}
    for name in plants.names():
        assert model(sim=name, **kw).sim == name
    with pytest.raises(ValidationError, match="unknown simulated plant 'warthog'"):
        model(sim="warthog", **kw)
    schema = model.model_json_schema()["properties"]["sim"]
    enums = [s.get("enum") for s in schema.get("anyOf", [schema]) if s.get("enum")]
    assert enums == [list(plants.names())]


def test_counter_range_is_the_boards() -> None:
    assert kinematics.COUNTER_RANGE == plants.enc_modulo() == lib.XRF_ICO_ENC_MODULO == 16384
    assert kinematics.signed14(16383) == -1 and kinematics.wrap_delta(2, 16380) == 6


def test_every_plant_has_its_profile_and_example() -> None:
    """Adding a plant is its plant file, its row, its kinematics, its profile and an example
    (docs/developers/adding-a-robot.md); the supervisor runs the example named after a plant on
    that plant."""
    repo = RT_SRC.parents[1]
    for name in plants.names():
        assert (repo / "deploy" / "profiles" / f"{name}.json").is_file(), name
        example = repo / "student_projects" / "examples" / name
        for part in ("CMakeLists.txt", "msg/Ros2Xeno.msg", "msg/Xeno2Ros.msg", "src/main.cpp", "README.md"):
            assert (example / part).is_file(), (name, part)
