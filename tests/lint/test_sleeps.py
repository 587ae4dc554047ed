"""No test synchronises by sleeping (issue 27): a bare `time.sleep` between two steps hopes the
machine was quick enough, and on this shared 2-core machine it sometimes is not (flaky) while on a
quiet one it wastes the whole nap (slow). A test waits for the event instead (`wait_for`,
`Server.wait_cycles`, `WsClient.wait_for`, Playwright's `wait_for_function`).

What stays: a sleep inside a polling loop (the loop waits for its condition), and a sleep whose
purpose *is* time passing (an idle session expiring, a window in which something must NOT
happen, a soak's length); that one says so in a comment on its line, which this check requires.
"""

from __future__ import annotations

import ast
from pathlib import Path

TESTS = Path(__file__).resolve().parents[1]


def bare_sleeps(source: str) -> list[int]:
    """Line numbers of `*.sleep(...)` calls outside any loop of their function with no comment on
    their line."""
    tree = ast.parse(source)
    lines = source.splitlines()
    parents: dict[ast.AST, ast.AST] = {}
    for node in ast.walk(tree):
        for child in ast.iter_child_nodes(node):
            parents[child] = node
    found = []
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "sleep"):
            continue
        up: ast.AST = node
        in_loop = False
        while up in parents:
            up = parents[up]
            if isinstance(up, (ast.While, ast.For, ast.AsyncFor)):
                in_loop = True
                break
            if isinstance(up, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                break
        if not in_loop and "#" not in lines[node.lineno - 1]:
            found.append(node.lineno)
    return found


def test_no_test_sleeps_to_synchronise() -> None:
    offenders = []
    for path in sorted(TESTS.rglob("*.py")):
        if "fixtures" in path.relative_to(TESTS).parts:  # programs the tests run, not tests
            continue
        offenders += [f"{path.relative_to(TESTS)}:{n}" for n in bare_sleeps(path.read_text())]
    assert not offenders, f"wait for the event, or say on the line why time must pass: {offenders}"


def test_the_check_finds_a_planted_bare_sleep() -> None:
    planted = (
        "import time\n"
        "def test_x(server):\n"
        "    server.start_run()\n"
        "    time.sleep(0.5)\n"  # the synchronising kind: found
        "    time.sleep(2)  # the point: idle for longer than the timeout\n"
        "    while not server.ready():\n"
        "        time.sleep(0.05)\n"  # polling: fine
        "    asyncio.sleep(1)\n"  # any sleep: found
    )
    assert bare_sleeps(planted) == [4, 8]
