"""What is written once stays written once (issue 27, "Still written more than once"):

- the frontend's HTML escaping and CSRF header: only in `frontend/lib.js` (a page had its own `esc`,
  and one copy had drifted: it showed null as "null");
- the appliance's defaults (the default plant/profile `relbot`, the SPI device, the dashboard's port
  8000, the room's MQTT ports 1883/8883): only in `Settings` (server/settings.py) and, for the room's
  broker, `room/topics.py`; code elsewhere reads them from there (`Settings.sim`, ...);
- the bundled examples' and templates' `Encoder.hpp` and `Pid.hpp`: each example or template is a
  self-contained project a student copies, zips and uploads, so each keeps its own copy; relbot's
  is the source and the others must be byte-identical to it;
- a template made from an example (the cell's, the youBot's: the homing, the arm and the closing
  sequence done, the control law left to the student) is its example outside the parts marked
  `>>> student part` ... `<<< student part`: a fix to the example's homing or arm reaches the template.

Each check is a function of a tree, run on the checkout (nothing found) and on a copy with a
planted second copy (found, naming the file). docs/ and tests/ may mention the values freely.
"""

from __future__ import annotations

import ast
import re
import shutil
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

# ---- the frontend -----------------------------------------------------------------------------

LIB = "frontend/lib.js"
# A definition of an escaping function, or the entity table one is made of.
ESC_DEFINITION = re.compile(
    r"function\s+esc\s*\(|\besc\s*=\s*(?:\(|function|[A-Za-z_$][\w$]*\s*=>)|[\"']&lt;[\"']|[\"']&quot;[\"']"
)
# The CSRF cookie read, or the header named.
CSRF = re.compile(r"xrf_csrf|X-CSRF-Token", re.IGNORECASE)


def frontend_files(root: Path) -> list[Path]:
    front = root / "frontend"
    return sorted(
        p for p in front.rglob("*") if p.suffix in (".js", ".html") and "vendor" not in p.relative_to(front).parts
    )


def frontend_copies(root: Path) -> list[str]:
    found = []
    for path in frontend_files(root):
        rel = path.relative_to(root).as_posix()
        if rel == LIB:
            continue
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if ESC_DEFINITION.search(line):
                found.append(f"{rel}:{n}: HTML escaping defined again (use xrf.esc / xrfLib.esc): {line.strip()}")
            if CSRF.search(line):
                found.append(f"{rel}:{n}: the CSRF header made again (use xrfLib.csrfHeaders / send): {line.strip()}")
    return found


# ---- defaults ---------------------------------------------------------------------------------

# file (under appliance/xrflab/) -> the values it may write, and why
DEFAULTS_HOME = {
    "server/settings.py": {"relbot", "/dev/spidev0.0", 8000},  # Settings: the one place
    "room/topics.py": {1883, 8883},  # the room's MQTT ports (stdlib only: `xrf room`'s parser reads them)
    # A fake loop for in-process tests reports a plant like a real loop does: a value, not a default.
    "channels/testloop.py": {"relbot"},
}
DEFAULT_INTS = {8000, 1883, 8883}


def _default_value(node: ast.Constant) -> object | None:
    v = node.value
    if isinstance(v, str):
        if v == "relbot":
            return "relbot"
        if "spidev0.0" in v:
            return "/dev/spidev0.0"
        port = re.search(r":(8000|1883|8883)\b", v)  # in a URL
        if port:
            return int(port.group(1))
    elif type(v) is int and v in DEFAULT_INTS:
        return v
    return None


def python_file_defaults(source: str, rel: str) -> list[str]:
    """The defaults written in one file under appliance/xrflab/ (`rel`) that are not its own to write.
    String and number constants only: docstrings and comments are prose, not read."""
    tree = ast.parse(source, rel)
    docstrings = {
        id(node.body[0].value)
        for node in ast.walk(tree)
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
        and node.body
        and isinstance(node.body[0], ast.Expr)
        and isinstance(node.body[0].value, ast.Constant)
    }
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and id(node) not in docstrings:
            value = _default_value(node)
            if value is not None and value not in DEFAULTS_HOME.get(rel, set()):
                found.append(f"appliance/xrflab/{rel}:{node.lineno}: {value!r} (read it from Settings)")
    return found


def python_defaults(root: Path) -> list[str]:
    base = root / "appliance" / "xrflab"
    found = []
    for path in sorted(base.rglob("*.py")):
        found += python_file_defaults(path.read_text(), path.relative_to(base).as_posix())
    return found


# Not Python: the lab script and deploy/. Comments may name the values; the udev rule must name the
# kernel's device itself, and a bench profile named relbot is data.
SCRIPT_VALUE = re.compile(r"\b(8000|1883|8883)\b|spidev0\.0|\brelbot\b")
SCRIPT_ALLOWED = ("deploy/profiles/", "deploy/udev/")


def script_defaults(root: Path) -> list[str]:
    found = []
    paths = [root / "lab", *sorted(p for p in (root / "deploy").rglob("*") if p.is_file())]
    for path in paths:
        rel = path.relative_to(root).as_posix()
        if rel.startswith(SCRIPT_ALLOWED):
            continue
        try:
            lines = path.read_text().splitlines()
        except UnicodeDecodeError:
            continue
        for n, line in enumerate(lines, 1):
            if not line.lstrip().startswith(("#", ";")) and SCRIPT_VALUE.search(line):
                found.append(f"{rel}:{n}: a default of Settings written again: {line.strip()}")
    return found


# ---- the examples' shared headers -------------------------------------------------------------

SHARED_HEADERS = ("Encoder.hpp", "Pid.hpp")
SOURCE_EXAMPLE = "relbot"


def example_headers(root: Path) -> list[str]:
    examples = root / "student_projects" / "examples"
    # The templates are projects a student starts from and zips whole too (the cell's and the
    # youBot's carry the headers): their copies are checked as the examples' are.
    projects = [*examples.iterdir(), *(root / "student_projects" / "templates").iterdir()]
    found = []
    for name in SHARED_HEADERS:
        source = examples / SOURCE_EXAMPLE / "include" / name
        for example in sorted(p for p in projects if (p / "include" / name).is_file()):
            copy = example / "include" / name
            if copy != source and copy.read_bytes() != source.read_bytes():
                found.append(
                    f"{copy.relative_to(root)} differs from {source.relative_to(root)} (the source): "
                    f"change relbot's and copy it to every example and template that has it"
                )
    return found


# ---- templates made from an example -----------------------------------------------------------

STUDENT_PART = re.compile(r"^[ \t]*// >>> student part.*?^[ \t]*// <<< student part[^\n]*\n", re.M | re.S)


def _code(text: str, name: str) -> str:
    """The code a template shares with its example: the student's parts, comments, the class's name,
    the log's file name and layout taken out (clang-format wraps a longer name differently)."""
    text = STUDENT_PART.sub("", text)
    text = re.sub(r"//[^\n]*", "", text)
    text = re.sub(r"\bTemplate\b", name, text).replace("TEMPLATE", name.upper())
    text = text.replace('"logs/template_', '"logs/')
    flat = " ".join(text.split())
    # A member initialiser list whose last entry was the student's ends one comma earlier.
    return re.sub(r",\s*\{", " {", flat)


def templates_from_examples(root: Path) -> list[str]:
    found = []
    for template in sorted((root / "student_projects" / "templates").iterdir()):
        example = root / "student_projects" / "examples" / template.name
        ours = template / "src" / "Template.cpp"
        if not (example.is_dir() and ours.is_file()):
            continue  # a template of its own (base, 20sim): nothing to follow
        names = [p.stem for p in (example / "src").glob("*.cpp") if p.name != "main.cpp"]
        if len(names) != 1:
            found.append(f"{example.relative_to(root)}: expected one controller source beside main.cpp, got {names}")
            continue
        name = names[0]
        for mine, theirs in (
            (ours, example / "src" / f"{name}.cpp"),
            (template / "include" / "Template.hpp", example / "include" / f"{name}.hpp"),
            (template / "src" / "main.cpp", example / "src" / "main.cpp"),
        ):
            if _code(mine.read_text(), name) != _code(theirs.read_text(), name):
                found.append(
                    f"{mine.relative_to(root)} differs from {theirs.relative_to(root)} outside the student's "
                    f"parts: make the change in both (or mark it `>>> student part` ... `<<< student part`)"
                )
    return found


CHECKS = (frontend_copies, python_defaults, script_defaults, example_headers, templates_from_examples)


@pytest.mark.parametrize("check", CHECKS, ids=lambda c: c.__name__)
def test_the_checkout_has_no_second_copy(check: Callable[[Path], list[str]]) -> None:
    assert check(REPO) == []


# ---- each check finds a planted copy ----------------------------------------------------------


@pytest.fixture(scope="module")
def tree(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """What the checks read, copied once; each test plants its copy in one file and takes it out."""
    root = tmp_path_factory.mktemp("written-once")
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info", "build", "vendor")
    for name in ("frontend", "deploy", "student_projects/examples", "student_projects/templates"):
        shutil.copytree(REPO / name, root / name, ignore=ignore)
    shutil.copy2(REPO / "lab", root / "lab")
    return root


@contextmanager
def planted(tree: Path, rel: str, text: str) -> Iterator[None]:
    path = tree / rel
    before = path.read_text()
    path.write_text(before + text)
    try:
        yield
    finally:
        path.write_text(before)


@pytest.mark.parametrize(
    "text",
    [
        'const esc = (s) => String(s).replace(/[&<>"\']/g, (c) => ({ "&": "&amp;", "<": "&lt;" }[c]));\n',
        "function esc(s) { return s; }\n",
        "xrf.escape = function (s) { return s.replace(/</g, '&lt;'); };\n",
    ],
)
def test_a_second_esc_is_found(tree: Path, text: str) -> None:
    with planted(tree, "frontend/pages/users.js", text):
        found = frontend_copies(tree)
    assert any(f.startswith("frontend/pages/users.js:") and "escaping" in f for f in found), found


@pytest.mark.parametrize(
    "text",
    [
        "const m = document.cookie.match(/(?:^|;\\s*)xrf_csrf=([^;]+)/);\n",
        'fetch(p, { method: "POST", headers: { "X-CSRF-Token": token } });\n',
    ],
)
def test_a_second_csrf_header_is_found(tree: Path, text: str) -> None:
    with planted(tree, "frontend/room.js", text):
        found = frontend_copies(tree)
    assert any(f.startswith("frontend/room.js:") and "CSRF" in f for f in found), found


@pytest.mark.parametrize(
    "text",
    [
        'DEFAULT_PLANT = "relbot"\n',
        'DEVICE = "/dev/spidev0.0"\n',
        "PORT = 8000\n",
        'URL = "http://127.0.0.1:8000"\n',
        "BROKER = (1883, 8883)\n",
    ],
)
def test_a_default_outside_settings_is_found(text: str) -> None:
    source = (REPO / "appliance/xrflab/doctor.py").read_text()
    assert python_file_defaults(source, "doctor.py") == []
    found = python_file_defaults(source + text, "doctor.py")
    assert found and all(f.startswith("appliance/xrflab/doctor.py:") for f in found), found


def test_a_default_in_a_deploy_script_is_found(tree: Path) -> None:
    with planted(tree, "deploy/install", "\nxrf serve --port 8000\n"):
        found = script_defaults(tree)
    assert [f for f in found if f.startswith("deploy/install:")], found


def test_a_drifted_example_header_is_found(tree: Path) -> None:
    with planted(tree, "student_projects/examples/stage/include/Pid.hpp", "// drifted\n"):
        found = example_headers(tree)
    assert [f for f in found if "stage/include/Pid.hpp" in f], found


def test_a_drifted_template_header_is_found(tree: Path) -> None:
    with planted(tree, "student_projects/templates/youbot/include/Encoder.hpp", "// drifted\n"):
        found = example_headers(tree)
    assert [f for f in found if "templates/youbot/include/Encoder.hpp" in f], found


@pytest.mark.parametrize(
    ("rel", "old", "new"),
    [
        # a homing constant changed in the example only
        ("student_projects/examples/cell/src/CellController.cpp", "homing_timeout_s = 20", "homing_timeout_s = 30"),
        # the arm's closing speed changed in the template only
        ("student_projects/templates/youbot/src/Template.cpp", "closing_speed = 20.0", "closing_speed = 40.0"),
        # a member dropped from the template's header
        ("student_projects/templates/youbot/include/Template.hpp", "    bool at_rest = false;\n", ""),
    ],
)
def test_a_template_drifted_from_its_example_is_found(tree: Path, rel: str, old: str, new: str) -> None:
    path = tree / rel
    before = path.read_text()
    assert old in before
    path.write_text(before.replace(old, new))
    try:
        found = templates_from_examples(tree)
    finally:
        path.write_text(before)
    assert [f for f in found if f.startswith(rel)] or [f for f in found if rel.split("/")[2] in f], found
    assert templates_from_examples(tree) == []
