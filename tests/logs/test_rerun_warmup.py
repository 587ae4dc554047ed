"""The live viewer's warm-up recording (logs/rerun_warmup.py, issue 31 bug 6): read by the pinned
rerun as a time series of its own application, nothing else in it (no blueprint, no other
recording), so that drawing it makes the viewer build its plots' render pipelines and closing it
leaves nothing of it behind. The tab's use of it (drawn hidden, closed before the run's data) is
tests/ui/test_rerun_live_edge_ui.py's."""

from __future__ import annotations

import math
import subprocess
import sys
import warnings
from pathlib import Path

import httpx

from xrf_testing.harness import Server
from xrflab.logs.rerun_warmup import APPLICATION, ENTITY, RECORDING_ID, SAMPLES, warmup_rrd

RERUN = Path(sys.executable).with_name("rerun")


def test_the_warmup_reads_back_as_one_time_series_of_its_own_application(tmp_path: Path) -> None:
    from rerun.chunk import RrdReader

    path = tmp_path / "warmup.rrd"
    path.write_bytes(warmup_rrd())
    verify = subprocess.run(
        [str(RERUN), "rrd", "verify", "--check-footers", "false", str(path)], capture_output=True, text=True
    )
    assert verify.returncode == 0, verify.stderr
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # no footer: rerun says it scans the file
        reader = RrdReader(path)
    assert reader.blueprints() == []
    (store,) = reader.recordings()
    # not the runs' application (rerun_wire.APPLICATION_ID): nothing of it joins a run's recording
    # or blueprint; the tab closes it by this id (frontend/rerun-tab.js WARMUP_STORE)
    assert (store.kind, store.application_id, store.recording_id) == ("recording", APPLICATION, RECORDING_ID)
    assert (APPLICATION, RECORDING_ID) == ("xrflab-warmup", "warmup")
    (chunk,) = list(reader.stream(store=store))
    batch = chunk.to_record_batch()
    assert batch.schema.metadata[b"rerun:entity_path"].decode() == ENTITY
    # the live recording's timelines and its kind of data: Scalars, two series a row
    assert batch.column("cycle").cast("int64").to_pylist() == list(range(SAMPLES))
    times = batch.column("time").cast("int64").to_pylist()
    assert times == sorted(times) and len(set(times)) == SAMPLES
    values = batch.column("Scalars:scalars").to_pylist()
    assert len(values) == SAMPLES and all(len(v) == 2 for v in values)
    assert values[16] == [math.sin(1), math.cos(1)]


def test_the_warmup_is_served_behind_the_login(server: Server) -> None:
    assert httpx.get(server.url + "/api/logs/rerun/warmup.rrd").status_code == 401
    r = server.http.get("/api/logs/rerun/warmup.rrd")
    assert r.status_code == 200 and r.content[:4] == b"RRF2", r.content[:8]
    assert r.headers["content-type"] == "application/octet-stream"
