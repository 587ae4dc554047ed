"""The fast tier (`./lab test --fast`, xrf_testing/tiers.py) selects no test that starts a process,
and still selects the in-process tests. Checked from outside: pytest's own collection (`--collect-
only --fast`) of a planted suite with one test of each kind, and of the real suite against what its
source says (the test functions' parameters, read with `ast`, not with the tier's bytecode walk)."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

# Fixtures that start an appliance, a browser, a broker, a loop or a build (the folders' conftests).
LIVE_FIXTURES = {
    "server",
    "running",
    "accounts",
    "free_bench",
    "browser",
    "raw_browser",
    "chromium_path",
    "broker",
    "lab",
    "probe",
    "probe_exe",
    "relbot_exe",
    "checker_exe",
    "run_loop",
    "running_loop",
    "procs",
    "peer",
    "debian_root",
}
# Whole folders of tests that need a browser or a Debian tree.
LIVE_FOLDERS = ("tests/ui/", "tests/deploy/")


def _collect(args: list[str], cwd: Path, env: dict[str, str] | None = None) -> list[str]:
    out = subprocess.run(
        [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode in (0, 5), out.stdout[-3000:] + out.stderr[-3000:]  # 5: nothing selected
    return [line for line in out.stdout.splitlines() if "::" in line]


def _parametrized(func: ast.FunctionDef | ast.AsyncFunctionDef) -> set[str]:
    """Names a `@pytest.mark.parametrize("a,b", ...)` gives values (not fixtures)."""
    names: set[str] = set()
    for deco in func.decorator_list:
        if isinstance(deco, ast.Call) and ast.unparse(deco.func).endswith("parametrize") and deco.args:
            first = deco.args[0]
            if isinstance(first, ast.Constant) and isinstance(first.value, str):
                names |= {n.strip() for n in first.value.split(",")}
    return names


def test_a_planted_suite_keeps_only_its_in_process_test(tmp_path: Path) -> None:
    suite = tmp_path / "suite"
    suite.mkdir()
    (suite / "conftest.py").write_text(
        textwrap.dedent(
            """
            import pytest
            from xrf_testing.harness import start_server

            pytest_plugins = ["xrf_testing.tiers"]

            @pytest.fixture
            def server(tmp_path):
                return start_server(tmp_path, tmp_path)  # never called: collection only
            """
        )
    )
    (suite / "helpers.py").write_text(
        textwrap.dedent(
            """
            import subprocess

            def compile_it():
                return subprocess.run(["cc", "--version"])
            """
        )
    )
    (suite / "test_kinds.py").write_text(
        textwrap.dedent(
            """
            import pytest
            from helpers import compile_it

            def test_pure():
                assert 1 + 1 == 2

            def test_uses_the_server_fixture(server):
                pass

            def test_calls_a_helper_that_runs_a_process():
                compile_it()

            def test_imports_a_starter_in_its_body(tmp_path):
                from xrf_testing.harness import start_server
                start_server(tmp_path, tmp_path)

            def test_calls_a_named_starter():
                from xrflab.build import build_project
                build_project()

            @pytest.mark.live
            def test_marked_by_hand():
                pass

            class TestGrouped:
                def test_method_pure(self):
                    pass

                def test_method_in_a_class_with_a_fixture(self, server):
                    pass
            """
        )
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "tests"), str(REPO / "appliance"), str(suite)])}
    args = ["-c", os.devnull, "--rootdir", str(suite), str(suite)]
    everything = _collect(args, suite, env)
    fast = _collect([*args, "--fast"], suite, env)
    assert len(everything) == 8, everything
    assert [n.split("::", 1)[1] for n in fast] == ["test_pure", "TestGrouped::test_method_pure"]
    live = _collect([*args, "-m", "live"], suite, env)
    assert len(live) == 6 and not set(live) & set(fast)


def test_the_real_fast_tier_has_no_live_test_and_most_in_process_ones() -> None:
    fast = _collect(["--fast", "tests"], REPO)
    assert len(fast) >= 500, f"only {len(fast)} tests in the fast tier"
    assert not [n for n in fast if n.startswith(LIVE_FOLDERS)]

    # every test function's own parameters, from the source
    params: dict[tuple[str, str], set[str]] = {}
    for path in sorted({n.split("::", 1)[0] for n in fast}):
        for node in ast.walk(ast.parse((REPO / path).read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and node.name.startswith("test"):
                params[(path, node.name)] = {a.arg for a in node.args.args} - _parametrized(node)
    offenders = []
    for nodeid in fast:
        path, name = nodeid.split("::", 1)
        name = name.rsplit("::", 1)[-1].split("[", 1)[0]
        if params.get((path, name), set()) & LIVE_FIXTURES:
            offenders.append(nodeid)
    assert not offenders, "tests with a live fixture in the fast tier:\n" + "\n".join(offenders)

    # and the in-process tests of the core modules are in it
    for path in (
        "tests/server/test_hub_queue.py",
        "tests/server/accounts/test_lease_logic.py",
        "tests/logs/test_runfolder.py",
        "tests/host/test_statemachine.py",
    ):
        assert any(n.startswith(path + "::") for n in fast), path
