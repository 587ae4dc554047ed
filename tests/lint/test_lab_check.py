"""`./lab check` fails on what it is there to catch, naming the file: a copy of the checkout with one
planted defect per part (a lint finding and an unformatted file, a type error, an unformatted C
file and a warning in rt_core, a shellcheck finding) is refused part by part.

The clean tree itself is checked by the whole suite's run (`./lab test` starts with `./lab check`)."""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def tree(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """What ./lab check reads, copied (appliance/, rt_core/, deploy/, the scripts, the configs), with
    the checkout's venv linked in so nothing is installed."""
    root = tmp_path_factory.mktemp("check")
    for name in ("lab", "pyproject.toml", "README.md"):
        shutil.copy2(REPO / name, root / name)
    (root / ".ci").mkdir()
    shutil.copy2(REPO / ".ci" / "run", root / ".ci" / "run")
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info", "build")
    for name in ("appliance", "rt_core", "deploy"):
        shutil.copytree(REPO / name, root / name, symlinks=True, ignore=ignore)
    (root / ".venv").symlink_to(REPO / ".venv")
    yield root
    shutil.rmtree(root, ignore_errors=True)


def check(root: Path, part: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST")}
    return subprocess.run(
        [str(root / "lab"), "check", part], cwd=root, env=env, capture_output=True, text=True, timeout=600
    )


@contextmanager
def planted(path: Path, text: str) -> Iterator[None]:
    original = path.read_text() if path.exists() else None
    path.write_text((original or "") + text)
    try:
        yield
    finally:
        if original is None:
            path.unlink()
        else:
            path.write_text(original)


def test_python_lint_and_format(tree: Path) -> None:
    bad = tree / "appliance" / "xrflab" / "planted_lint.py"
    for text, finding in [
        ("import os\n", "F401"),  # unused import
        ("x = {  'a':1 }\n", "planted_lint.py"),  # lints clean, but not formatted
    ]:
        with planted(bad, text):
            proc = check(tree, "python")
            assert proc.returncode != 0, proc.stdout + proc.stderr
            assert finding in proc.stdout + proc.stderr
    assert check(tree, "python").returncode == 0


def test_types(tree: Path) -> None:
    bad = tree / "appliance" / "xrflab" / "planted_types.py"
    with planted(bad, "def half(n: int) -> int:\n    return n / 2\n"):
        proc = check(tree, "types")
        assert proc.returncode != 0
        assert "planted_types.py:2" in proc.stdout + proc.stderr


def test_c_format_and_warnings(tree: Path) -> None:
    src = tree / "rt_core" / "src" / "plants.c"
    with planted(src, "\nint  xrf_planted_format (void) { return 0 ; }\n"):
        proc = check(tree, "c")
        assert proc.returncode != 0
        assert "plants.c" in proc.stderr
    # Formatted, but a warning (-Wunused-variable) that -Werror turns into a failed build.
    with planted(src, "\nint xrf_planted_warning(void)\n{\n    int unused = 1;\n    return 0;\n}\n"):
        proc = check(tree, "c")
        assert proc.returncode != 0
        assert "unused" in proc.stderr and "Werror" in proc.stderr


def test_shell(tree: Path) -> None:
    script = tree / "deploy" / "planted.sh"
    with planted(script, "#!/bin/sh\nrm -rf $1/data\n"):
        script.chmod(0o755)
        proc = check(tree, "shell")
        assert proc.returncode != 0
        assert "planted.sh" in proc.stdout and "SC2086" in proc.stdout


def test_unknown_part_is_refused(tree: Path) -> None:
    proc = check(tree, "spelling")
    assert proc.returncode == 2
    assert "unknown check 'spelling'" in proc.stderr
