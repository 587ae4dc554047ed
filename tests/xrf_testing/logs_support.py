"""Helpers for the logging tests through the appliance (tests/logs, tests/server): a real server (tests/xrf_testing/harness.py)
whose bundled projects are the loop probe (all six log types every cycle) and the logger-cost
controller (N doubles every cycle, bench/logs/logger_cost_project)."""

from __future__ import annotations

from pathlib import Path

from xrf_testing.harness import Server, shared_builds_root, start_server, wait_for  # noqa: F401 (wait_for: re-exported)

REPO = Path(__file__).resolve().parents[2]

PROBE = "logs-probe"
COST = "logs-cost"


def projects_dir() -> Path:
    """A stable folder of symlinks (the shared build folders' CMake caches remember the source
    path, so it must not change between sessions)."""
    root = REPO / ".cache" / "logs-appliance-projects" / "examples"
    root.mkdir(parents=True, exist_ok=True)
    for name, target in ((PROBE, REPO / "tests/fixtures/loop_probe"), (COST, REPO / "bench/logs/logger_cost_project")):
        link = root / name
        if not link.is_symlink():
            link.symlink_to(target)
    return root.parent


def start(data_dir: Path, **settings) -> Server:
    return start_server(data_dir, shared_builds_root(), projects_dir=str(projects_dir()), **settings)
