"""Log files written by a real loop process (tests/fixtures/loop_probe) decode completely."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
import pytest

from xrf_testing.loops import LoopProcess, build_probe
from xrflab.logs import open_log
from xrflab.logs.convert import convert


@pytest.fixture(scope="module")
def probe(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_probe(tmp_path_factory.mktemp("probe-build"))


@pytest.fixture
def loop(probe: Path, shm_name: str, tmp_path: Path):
    started: list[LoopProcess] = []

    def start() -> LoopProcess:
        lp = LoopProcess(probe, shm_name, tmp_path, capture=False, XRF_LOG_DIR=str(tmp_path / "data"))
        started.append(lp)
        return lp

    yield start
    for lp in started:
        lp.stop()


def _check_probe_values(rec: np.ndarray) -> None:
    """The probe logs c, c odd, 'a' + c % 26, c, c * 0.5f, c * 0.25 (tests/fixtures/loop_probe)."""
    c = rec["cycle_2"]
    assert np.array_equal(rec["count"], c.astype(np.int32))
    assert np.array_equal(rec["flag"], (c & 1) == 1)
    assert np.array_equal(np.ascontiguousarray(rec["letter"]).view(np.uint8), (97 + c % 26).astype(np.uint8))
    assert np.array_equal(rec["ratio"], c.astype(np.float32) * np.float32(0.5))
    assert np.array_equal(rec["value"], c * 0.25)


def test_loop_log_decodes_with_continuous_seq(loop, tmp_path: Path) -> None:
    lp = loop()
    lp.command("initialise", "INITIALISED")
    lp.command("start", "RUN")
    lp.wait_cycles(300)
    lp.command("stop", "STOPPED")
    lp.ch.send_command("quit")  # the loop leaves at once; QUIT is never observable
    assert lp.proc.wait(10) == 0
    files = list((tmp_path / "data" / "logs").glob("probe_*.xrf"))
    assert len(files) == 1
    log = open_log(files[0])
    assert log.skipped == [] and log.lost == 0 and len(log.segments) == 1
    rec = log.records
    assert len(rec) >= 300
    assert np.array_equal(rec["seq"], np.arange(len(rec), dtype=np.uint64))
    assert np.all(np.diff(rec["cycle"].astype(np.int64)) >= 1) and np.all(np.diff(rec["t_ns"]) > 0)
    assert log.segments[0].header["cycle_freq"] == 1000
    _check_probe_values(rec)
    import pyarrow.parquet as pq

    table = pq.read_table(convert(files[0], "parquet"))
    assert np.array_equal(table.column("value").to_numpy(), rec["value"])


def test_kill_9_mid_run_decodes_to_the_last_complete_record(loop, tmp_path: Path) -> None:
    lp = loop()
    lp.command("initialise", "INITIALISED")
    lp.command("start", "RUN")
    lp.wait_cycles(500)
    os.kill(lp.proc.pid, signal.SIGKILL)
    lp.proc.wait(5)
    path = next((tmp_path / "data" / "logs").glob("probe_*.xrf"))
    log = open_log(path)
    seg = log.segments[0]
    stride = log.records.dtype.itemsize
    data = seg.offset + (16 + int.from_bytes(path.read_bytes()[8:12], "little") + 7) // 8 * 8
    complete = (path.stat().st_size - data) // stride
    assert len(log.records) == complete >= 100
    assert log.skipped_bytes == (path.stat().st_size - data) % stride
    assert np.array_equal(log.records["seq"], np.arange(complete, dtype=np.uint64))
    _check_probe_values(log.records)
    # And a partial last record, as a crash mid-write would leave it, is dropped with a note.
    cut = tmp_path / "cut.xrf"
    cut.write_bytes(path.read_bytes()[: data + (complete - 1) * stride + 17])
    log = open_log(cut)
    assert len(log.records) == complete - 1 and "17 bytes" in log.skipped[0]
