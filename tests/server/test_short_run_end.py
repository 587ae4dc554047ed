"""A loop that ends while its start is still under way is ended, not left "running".

The run's exit task (Supervisor._watch_exit) was created before the start opened the shared
memory; a short run (`max_cycles`) on a loaded machine could end, and have its end recorded, before
the start had marked it running and started its logging and tasks: the start then marked the ended
run "running" and started a log writer nobody would stop. The run stayed "running" for good and the
bench with it (CI, session 13: `test_log_paths.py` waited 60 s for a 10-cycle run's end). Now the
end waits for the start (Run.settled) and drains the log as for any run.

The race needs the loop's exit to land inside the start's few milliseconds: stress-ng on every core
makes that likely (before the fix, 2 of the first 3 short runs under it stayed "running"; none of 25
without it). Each of RUNS one-cycle runs must end with its cycle in the record.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from xrf_testing.harness import Server, shared_builds_root, start_server, stop_server

RUNS = 20
END_WITHIN_S = 60.0  # a run's end on a machine loaded on every core (not a timing claim: a hang is forever)


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    s = start_server(tmp_path_factory.mktemp("data"), shared_builds_root())
    yield s
    stop_server(s)


@pytest.fixture
def loaded() -> Iterator[None]:
    stress_ng = shutil.which("stress-ng")
    assert stress_ng, "stress-ng is installed by ./lab"
    p = subprocess.Popen([stress_ng, "--cpu", str(os.cpu_count() or 2), "--timeout", "600s", "--quiet"])
    try:
        yield
    finally:
        p.terminate()
        p.wait(30)


def _status(server: Server, run_id: int) -> dict:
    r = server.http.get(f"/api/logs/runs/{run_id}")
    assert r.status_code == 200, r.text
    return r.json()["run"]


def test_runs_that_end_during_their_start_are_ended(server: Server, loaded: None, tmp_path: Path) -> None:
    ended: list[int] = []
    for _ in range(RUNS):
        server.stop_run()
        run_id = server.start_run("relbot", max_cycles=1)["id"]
        deadline = time.monotonic() + END_WITHIN_S
        while (run := _status(server, run_id))["status"] == "running":
            assert time.monotonic() < deadline, (
                f"run {run_id} still 'running' {END_WITHIN_S:.0f} s after its one cycle: {run}"
            )
            time.sleep(0.1)  # polling the record, as a page does
        assert run["status"] == "ended", run
        ended.append(run_id)
    assert len(ended) == RUNS
    # The bench is free: another run starts (a start left half done would hold it).
    server.stop_run()
    again = server.start_run("relbot", max_cycles=1)
    assert again["id"] > ended[-1]
