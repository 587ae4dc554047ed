"""Property-based fuzzing of the whole HTTP API against its own OpenAPI schema (schemathesis):
valid and invalid inputs for every operation, as a logged-in educator (the role that reaches
every handler) and anonymously. No response may be a 5xx. Bounded: a few examples per
operation and mode, well under a minute."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest
import requests
import schemathesis
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis.errors import Unsatisfiable
from schemathesis import GenerationMode

from xrf_testing.harness import Server, shared_builds_root, start_server, stop_server

EXAMPLES = 4
# Operations that would log the fuzzing session out or lock it (they are tested on their own).
SKIP = {("POST", "/api/auth/logout"), ("POST", "/api/users/{user_id}/reset")}


@pytest.fixture(scope="module")
def fuzz_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    # Its own appliance: fuzzed logins trip the rate limits of their address.
    s = start_server(tmp_path_factory.mktemp("data"), shared_builds_root(), login_max_failures_address=10**6)
    yield s
    stop_server(s)


def session_of(server: Server, logged_in: bool) -> requests.Session:
    session = requests.Session()
    session.headers["Origin"] = server.url
    if logged_in:
        for name in ("xrf_session", "xrf_csrf"):
            session.cookies.set(name, server.http.cookies.get(name))
        session.headers["X-CSRF-Token"] = server.http.headers["X-CSRF-Token"]
    return session


@pytest.mark.timeout(240)
@pytest.mark.parametrize("logged_in", [True, False], ids=["educator", "anonymous"])
def test_no_server_errors(fuzz_server: Server, logged_in: bool) -> None:
    raw = fuzz_server.http.get("/openapi.json").json()
    schema = schemathesis.openapi.from_dict(raw)
    session = session_of(fuzz_server, logged_in)
    failures: list[str] = []
    calls = 0
    t0 = time.monotonic()
    for result in schema.get_all_operations():
        op = result.ok()
        if (op.method.upper(), op.path) in SKIP:
            continue
        # Anonymous: valid requests only (everything but the login answers 401 before validation).
        modes = (GenerationMode.POSITIVE, GenerationMode.NEGATIVE) if logged_in else (GenerationMode.POSITIVE,)
        for mode in modes:

            @settings(
                max_examples=EXAMPLES,
                deadline=None,
                database=None,
                phases=[Phase.generate],
                suppress_health_check=list(HealthCheck),
            )
            @given(case=op.as_strategy(generation_mode=mode))
            def check(case) -> None:  # type: ignore[no-untyped-def]
                nonlocal calls
                calls += 1
                try:
                    response = case.call(base_url=fuzz_server.url, session=session, timeout=30)
                except requests.RequestException as exc:
                    failures.append(f"{case.method} {case.formatted_path}: {exc}")
                    return
                if response.status_code >= 500:
                    failures.append(
                        f"{case.method} {case.formatted_path} -> {response.status_code}: "
                        f"{response.text[:200]} ({case.as_curl_command()[:300]})"
                    )

            try:
                check()
            except Unsatisfiable:  # nothing invalid to send (e.g. a GET without parameters)
                pass
    assert calls > 100
    assert not failures, f"{len(failures)} server errors in {calls} calls:\n" + "\n".join(failures[:20])
    # Still logged in afterwards: fuzzing did not lock the session out.
    if logged_in:
        assert session.get(fuzz_server.url + "/api/me").status_code == 200
    print(f"{calls} calls in {time.monotonic() - t0:.1f} s")
