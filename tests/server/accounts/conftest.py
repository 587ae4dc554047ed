"""Fixtures for the accounts tests: a real appliance (tests/xrf_testing/harness.py) with one
account per role, each logged in through the real login endpoint."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from xrf_testing.accounts_support import Account, make_account
from xrf_testing.harness import Server, shared_builds_root, start_server, stop_server


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    s = start_server(tmp_path_factory.mktemp("data"), shared_builds_root(), lease_idle_s=600.0)
    yield s
    stop_server(s)


@pytest.fixture(scope="module")
def accounts(server: Server) -> Iterator[dict[str, Account]]:
    """student, student2, observer, educator2: logged-in clients of each."""
    made = {
        name: make_account(server, name, role)
        for name, role in (
            ("student", "student"),
            ("student2", "student"),
            ("observer", "observer"),
            ("educator2", "educator"),
        )
    }
    yield made
    for a in made.values():
        a.http.close()


@pytest.fixture
def free_bench(server: Server) -> Iterator[None]:
    """No run and a free lease before and after the test."""
    _free(server)
    yield
    _free(server)


def _free(server: Server) -> None:
    server.stop_run()
    for _ in range(10):  # a release hands the bench to the next in the queue: until nobody holds it
        if server.http.get("/api/lease").json()["holder"] is None:
            return
        server.http.post("/api/lease/release")
