"""`./lab check layers` (tests/lint/layers.py): the import graph of appliance/xrflab has no cycle and
every import points down the layers. The checkout passes; a copy of the package with one planted
back-import (inside a function, where a deferred import hides) or one planted cycle fails, naming it.

A planted copy is compared with the same copy unplanted, so these tests say what the tool finds
whatever state the rest of the tree is in."""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
TOOL = REPO / "tests" / "lint" / "layers.py"


# The tool, loaded from its file (tests/lint is no package): called in-process, so every test here
# but the one through ./lab is in the fast tier.
_spec = importlib.util.spec_from_file_location("lint_layers", TOOL)
assert _spec is not None and _spec.loader is not None
layers = importlib.util.module_from_spec(_spec)
sys.modules["lint_layers"] = layers  # its dataclass looks its module up while the module runs
_spec.loader.exec_module(layers)


def problems(appliance: Path) -> list[str]:
    return layers.check(appliance)


@pytest.fixture
def tree(tmp_path: Path) -> Path:
    """What `./lab check layers` reads, copied: ./lab, the tool, the package; the venv linked."""
    for name in ("lab", "pyproject.toml", "README.md"):
        shutil.copy2(REPO / name, tmp_path / name)
    (tmp_path / "tests" / "lint").mkdir(parents=True)
    shutil.copy2(TOOL, tmp_path / "tests" / "lint" / "layers.py")
    shutil.copytree(
        REPO / "appliance" / "xrflab",
        tmp_path / "appliance" / "xrflab",
        ignore=shutil.ignore_patterns("__pycache__", "*.so", "*.egg-info"),
    )
    (tmp_path / ".venv").symlink_to(REPO / ".venv")
    return tmp_path


def plant(path: Path, text: str) -> None:
    path.write_text(path.read_text() + text)


def new_lines(tree: Path, before: list[str]) -> list[str]:
    """What the tool reports in the planted tree that it did not report before planting."""
    return [line for line in problems(tree / "appliance") if line not in set(before)]


def test_the_checkout_has_no_cycle_and_no_back_import() -> None:
    found = problems(REPO / "appliance")
    assert found == [], "\n".join(found)


def test_lab_check_fails_on_a_planted_back_import(tree: Path) -> None:
    """A domain module reaching up into a service, from inside a function (a deferred import is
    still an import): `./lab check layers` fails and names both modules and both layers."""
    before = problems(tree / "appliance")
    runfolder = tree / "appliance" / "xrflab" / "runfolder.py"
    plant(runfolder, "\n\ndef _planted() -> None:\n    from . import credentials  # noqa: F401\n")
    line = runfolder.read_text().splitlines().index("    from . import credentials  # noqa: F401") + 1

    assert new_lines(tree, before) == [
        f"{runfolder}:{line}: xrflab.runfolder imports xrflab.credentials (layer domain → services)"
    ]
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST")}
    proc = subprocess.run(
        [str(tree / "lab"), "check", "layers"], cwd=tree, env=env, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode != 0
    assert "xrflab.runfolder imports xrflab.credentials (layer domain → services)" in proc.stdout
    assert "./lab check failed: layers" in proc.stderr


def test_a_service_importing_a_route_is_refused(tree: Path) -> None:
    before = problems(tree / "appliance")
    plant(tree / "appliance" / "xrflab" / "viz" / "scene.py", "\nimport xrflab.server.http.viz  # noqa: E402, F401\n")
    [found] = new_lines(tree, before)
    assert found.endswith("xrflab.viz.scene imports xrflab.server.http.viz (layer services → routes)")


def test_a_planted_cycle_is_named(tree: Path) -> None:
    """Two modules of one layer importing each other: allowed by the layers, refused as a cycle."""
    before = problems(tree / "appliance")
    pkg = tree / "appliance" / "xrflab"
    plant(pkg / "records.py", "\nfrom . import runfolder  # noqa: E402, F401\n")
    plant(pkg / "runfolder.py", "\nfrom .records import column  # noqa: E402, F401\n")
    assert new_lines(tree, before) == ["cycle: xrflab.records → xrflab.runfolder → xrflab.records"]


def test_a_module_in_no_layer_is_refused(tree: Path) -> None:
    """A new module is placed on purpose: one the table does not cover is an error."""
    before = problems(tree / "appliance")
    (tree / "appliance" / "xrflab" / "server" / "planted.py").write_text('"""Nowhere yet."""\n')
    [found] = new_lines(tree, before)
    assert "xrflab.server.planted is in no layer" in found


def test_a_module_that_does_not_parse_is_a_problem_not_a_traceback(tree: Path) -> None:
    """A merge's conflict markers left in a module: the check names it and fails cleanly."""
    before = problems(tree / "appliance")
    plant(tree / "appliance" / "xrflab" / "records.py", "<<<<<<< HEAD\n")
    [found] = new_lines(tree, before)
    assert "xrflab.records does not parse" in found


# ---- the drawing in docs/developers/architecture.md --------------------------------------------

ARCHITECTURE = REPO / "docs" / "developers" / "architecture.md"


def drawn_layers(text: str) -> dict[str, str]:
    """Every path the "## Layers" drawing names (`server/runs/`, `logs/{live,host_writer}.py`...)
    mapped to the layer it is drawn in: a line starting with a layer's name opens that layer, the
    lines below it continue it; words in parentheses are prose, not paths."""
    import re

    section = text.split("## Layers", 1)[1]
    drawing = section.split("```", 2)[1]
    out: dict[str, str] = {}
    layer = ""
    for line in drawing.splitlines():
        head = line.split()[0] if line.split() else ""
        if head in layers.LAYERS:
            layer = head
        line = re.sub(r"\([^)]*\)", "", line)  # "(but roles)", "(start a process, ...)"
        for token in re.findall(r"[\w/]+(?:\{[\w,]+\})?[\w/]*(?:\.py|/)", line):
            m = re.fullmatch(r"([\w/]*)\{([\w,]+)\}(\.py|/)?", token)
            names = [f"{m.group(1)}{n}{m.group(3) or ''}" for n in m.group(2).split(",")] if m else [token]
            for name in names:
                out[name] = layer
    return out


def drawing_problems(text: str) -> list[str]:
    modules = layers.module_names(REPO / "appliance")
    drawn = drawn_layers(text)
    assert len(drawn) > 30, drawn  # the parser found the drawing
    wrong = []
    for path, layer in drawn.items():
        module = layers.PACKAGE + "." + path.removesuffix("/").removesuffix(".py").replace("/", ".")
        if module not in modules:
            wrong.append(f"{path}: no such module")
        elif layers.layer_of(module) != layer:
            wrong.append(f"{path}: drawn in {layer}, LAYER_OF says {layers.layer_of(module)}")
    return wrong


def test_the_drawing_names_real_modules_in_their_layers() -> None:
    assert drawing_problems(ARCHITECTURE.read_text()) == []


def test_the_drawing_check_sees_a_misplaced_module() -> None:
    text = ARCHITECTURE.read_text()
    text = text.replace("  domain    errors.py,", "  domain    errors.py, server/app.py, server/nothing.py,", 1)
    assert sorted(drawing_problems(text)) == [
        "server/app.py: drawn in domain, LAYER_OF says roots",
        "server/nothing.py: no such module",
    ]
