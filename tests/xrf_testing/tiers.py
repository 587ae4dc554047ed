"""The fast tier (`./lab test --fast`, pytest's `--fast`): in-process tests only.

A test is *live* (full tier only) when anything it runs starts another process: an appliance
(`harness.start_server`), a build (CMake), a loop process, chromium, mosquitto, ros, a sandbox.
Nobody keeps a list of live tests: the classification reads the code. For each collected test it
walks the bytecode of the test function and of every fixture in its closure (conftests' too),
following calls into functions and classes defined under tests/ (so `xrf_testing` helpers are
looked through), and the test is live when it reaches

- the `subprocess` module (any use of it), or
- a name in `STARTERS` (the in-process entry points that start processes: they live in the
  appliance, whose code is not walked), or
- a `live` mark set by hand (`pytestmark = pytest.mark.live`) for what the walk cannot see.

`--fast` deselects live tests, and in the tests it keeps a child process is an error
(`subprocess.Popen` raises): a test the walk classified wrongly fails loudly in the fast tier
instead of making it slow. `tests/testing/test_fast_tier.py` checks the selection from outside.
"""

from __future__ import annotations

import importlib
import inspect
import subprocess
import sys
import types
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

TESTS = Path(__file__).resolve().parents[1]

# Appliance (or library) entry points that start a process or a server; the walk does not enter
# the appliance's code, so these are named. A new one goes here (the fast tier's Popen guard
# says so when it is missed).
STARTERS = frozenset(
    {
        "start_server",  # xrf_testing.harness: the appliance in a subprocess
        "build_project",  # xrflab.build: CMake
        "build_in_sandbox",
        "upload_and_build",
        "BrokerProcess",  # xrflab.room.broker: mosquitto
        "start_broker",
        "sync_playwright",  # chromium
        "popen_tied",
        "LoopProcess",
        "create_subprocess_exec",  # asyncio's
        "create_subprocess_shell",
        "Builder",  # xrflab.projects.builder: sandboxed CMake builds
        "run_selfcheck",  # xrflab.selfcheck: the xrf-selfcheck tool
        "SelfCheck",
        "build_interface_package",  # xrflab.ros.interfaces: colcon
        "convert_in_child",  # xrflab.logs.convert_child: a download's conversion
    }
)

# Helper packages of the suite whose modules a test imports inside its body (`from
# xrf_testing.logs_support import start`): the walk resolves those names there.
HELPER_PACKAGES = ("xrf_testing.",)

FAST_OPTION = "--fast"

# Fixtures around every test, not part of any: the session's leak check (it reads the process
# table once before and once after the session) and this module's guard.
AROUND_EVERY_TEST = frozenset({"nothing_left_behind", "_no_child_process_in_the_fast_tier"})


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        FAST_OPTION,
        action="store_true",
        help="the fast tier: only tests that start no process (no appliance, build, loop, browser, broker)",
    )


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", "live: starts a process (appliance, build, loop, browser, broker); not in the fast tier"
    )
    config.addinivalue_line(
        "markers",
        "rt_hog: makes a real-time thread spin on purpose (a hung loop, RLIMIT_RTTIME's spinners); "
        "`./lab test` runs these after the parallel part, alone (another worker's loop on the same "
        "CPU got no cycle meanwhile and was declared hung)",
    )


class _Walker:
    """Does a function (with what it calls under `roots`) start a process? Memoised per code object."""

    def __init__(self, roots: tuple[Path, ...] = (TESTS,)) -> None:
        self._seen: dict[types.CodeType, str | None] = {}
        self._roots = roots

    def why_live(self, obj: Any) -> str | None:
        func = inspect.unwrap(getattr(obj, "__func__", obj))
        code = getattr(func, "__code__", None)
        if code is None:
            return None
        return self._code(code, getattr(func, "__globals__", {}))

    def _code(self, code: types.CodeType, globs: dict[str, Any]) -> str | None:
        if code in self._seen:
            return self._seen[code]
        self._seen[code] = None  # recursion guard: a cycle adds nothing
        why = None
        local_imports = [n for n in code.co_names if n.startswith(HELPER_PACKAGES)]
        if local_imports:
            globs = dict(globs)
            for module in local_imports:
                for key, value in vars(importlib.import_module(module)).items():
                    globs.setdefault(key, value)
        for name in code.co_names:
            why = self._name(name, globs)
            if why:
                break
        if why is None:
            for const in code.co_consts:  # nested functions, lambdas, comprehensions
                if isinstance(const, types.CodeType):
                    why = self._code(const, globs)
                    if why:
                        break
        self._seen[code] = why
        return why

    def _name(self, name: str, globs: dict[str, Any]) -> str | None:
        if name in STARTERS:
            return name
        value = globs.get(name)
        if value is subprocess:
            return "subprocess"
        if isinstance(value, type) and self._ours(value):
            for attr in vars(value).values():
                why = self.why_live(attr)
                if why:
                    return f"{name} -> {why}"
            return None
        if callable(value):
            value = inspect.unwrap(value)  # @contextmanager, functools.wraps: the code is inside
        if callable(value) and self._ours(value):
            why = self.why_live(value)
            return f"{name} -> {why}" if why else None
        return None

    def _ours(self, obj: Any) -> bool:
        """Defined in the suite (walked), not in the appliance or a library (named in STARTERS)."""
        module = getattr(obj, "__module__", None)
        code = getattr(getattr(obj, "__func__", obj), "__code__", None)
        path = code.co_filename if code is not None else getattr(sys.modules.get(module or ""), "__file__", "")
        try:
            return bool(path) and any(Path(path).resolve().is_relative_to(r) for r in self._roots)
        except (TypeError, ValueError):
            return False


def why_live(item: pytest.Item, walker: _Walker) -> str | None:
    """Why the test is live (a path of names to the starter), or None for an in-process test."""
    mark = item.get_closest_marker("live")
    if mark is not None:
        return "marked live"
    why = walker.why_live(getattr(item, "obj", None))
    if why:
        return f"{item.name} -> {why}"
    info = getattr(item, "_fixtureinfo", None)
    for name in item.fixturenames if info is not None else ():
        if name in AROUND_EVERY_TEST:
            continue
        for fixturedef in info.name2fixturedefs.get(name, ()):
            why = walker.why_live(fixturedef.func)
            if why:
                return f"fixture {name} -> {why}"
    return None


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    # A suite outside tests/ (test_fast_tier.py plants one) has its own helpers walked too.
    root = config.rootpath.resolve()
    walker = _Walker((TESTS,) if TESTS.is_relative_to(root) else (TESTS, root))
    fast, live = [], []
    for item in items:
        why = why_live(item, walker)
        if why:
            item.add_marker(pytest.mark.live)
            item.user_properties.append(("live", why))
            live.append(item)
        else:
            fast.append(item)
    if config.getoption(FAST_OPTION):
        config.hook.pytest_deselected(items=live)
        items[:] = fast


class ChildProcessInFastTier(AssertionError):
    pass


@pytest.fixture(autouse=True)
def _no_child_process_in_the_fast_tier(request: pytest.FixtureRequest) -> Iterator[None]:
    """Under --fast, a test that starts a process was classified wrongly: fail it and say how to
    fix it, so the tier stays in-process."""
    if not request.config.getoption(FAST_OPTION):
        yield
        return
    real_init = subprocess.Popen.__init__

    def refuse(self: subprocess.Popen[Any], args: Any, *a: Any, **kw: Any) -> None:
        raise ChildProcessInFastTier(
            f"{request.node.nodeid} started a process ({args!r}) in the fast tier: add what starts it "
            "to STARTERS in tests/xrf_testing/tiers.py or mark the test `pytest.mark.live`"
        )

    subprocess.Popen.__init__ = refuse  # type: ignore[method-assign]
    try:
        yield
    finally:
        subprocess.Popen.__init__ = real_init  # type: ignore[method-assign]
