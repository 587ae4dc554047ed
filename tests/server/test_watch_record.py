"""xrf-watch's record in a run folder, read back by the restarted appliance
(server/runs/watch_record.py): the folder is the guest's to write, so the record is untrusted. A
link planted at its name is not followed, a huge file or a FIFO is refused without being read
whole (or blocking), a record with a field out of range or one too many is refused with why,
and a true record (as rt_core/tools/watch/main.c writes it) gives the outcome the run shows."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import pytest

from xrflab.channels import lib
from xrflab.server.runs import watch_record

TRUE = {
    "xrf_watch": 1,
    "pid": 4242,
    "loop": 4243,
    "reason": lib.XRF_WATCH_HOST_GONE,
    "done": 1,
    "event_unix_ms": 1_800_000_000_123,
    "safe_after_ns": 51_000,
    "rest_after_ns": 7_912_000_000,
    "drop_urad": 4_500,
    "hold_phase": lib.XRF_HOLD_PHASE_REST,
    "kill_status": 0,
    "hold_status": 0,
}


def _write(run_dir: Path, record: dict | bytes) -> None:
    data = record if isinstance(record, bytes) else (json.dumps(record) + "\n").encode()
    (run_dir / watch_record.RECORD).write_bytes(data)


def test_a_true_record_gives_the_outcome(tmp_path: Path) -> None:
    _write(tmp_path, TRUE)
    got = watch_record.read(tmp_path)
    assert got.problem == "" and got.pid == 0  # done: nobody to wait for
    o = got.outcome
    assert o == {
        "by": "xrf-watch",
        "reason": "host_gone",
        "done": True,
        "at": 1_800_000_000.123,
        "safe_ms": 0.051,
        "drop_deg": round(math.degrees(4.5e-3), 3),
        "rest_s": 7.912,
        "phase": "rest",
        "loop_killed": True,
    }
    text = watch_record.describe(o)
    assert "killed the loop" in text and "at rest 7.9 s after" in text and "0.26°" in text


def test_a_record_not_done_names_its_watcher(tmp_path: Path) -> None:
    _write(tmp_path, {**TRUE, "done": 0, "rest_after_ns": 0, "hold_phase": lib.XRF_HOLD_PHASE_CLOSING})
    got = watch_record.read(tmp_path)
    assert got.outcome is not None and got.outcome["rest_s"] is None and got.outcome["phase"] == "closing"
    assert got.pid == 4242
    assert "not at rest yet" in watch_record.describe(got.outcome)


def test_no_record_is_no_problem(tmp_path: Path) -> None:
    assert watch_record.read(tmp_path) == watch_record.Read(None, "")
    assert watch_record.read(tmp_path / "gone") == watch_record.Read(None, "")


def test_a_planted_link_is_not_followed(tmp_path: Path) -> None:
    secret = tmp_path / "secret.json"
    secret.write_text(json.dumps(TRUE))  # a true record elsewhere: still not read through a link
    run = tmp_path / "run"
    run.mkdir()
    (run / watch_record.RECORD).symlink_to(secret)
    got = watch_record.read(run)
    assert got.outcome is None and "refused" in got.problem


def test_a_huge_file_or_a_fifo_is_refused_without_reading_it(tmp_path: Path) -> None:
    path = tmp_path / watch_record.RECORD
    with open(path, "wb") as f:
        f.truncate(1 << 40)  # 1 TiB, sparse: read whole it would take the appliance down
    got = watch_record.read(tmp_path)
    assert got.outcome is None and f"over {watch_record.MAX_BYTES} bytes" in got.problem
    path.unlink()
    os.mkfifo(path)  # nobody writes it: an open or read that blocks would hang the restart
    got = watch_record.read(tmp_path)
    assert got.outcome is None and "not a regular file" in got.problem


@pytest.mark.parametrize(
    "bad",
    [
        {**TRUE, "drop_urad": -1},
        {**TRUE, "reason": 99},
        {**TRUE, "hold_phase": 7},
        {**TRUE, "done": True},  # a bool is not the integer xrf-watch writes
        {**TRUE, "safe_after_ns": 1e3},
        {**TRUE, "pid": 2**40},
        {**TRUE, "extra": "x" * 100},
        {k: v for k, v in TRUE.items() if k != "loop"},
        [TRUE],
        b"\xff\xfe not ascii",
        b'{"xrf_watch": 1',
    ],
)
def test_a_false_record_is_refused_with_why(tmp_path: Path, bad) -> None:  # noqa: ANN001
    _write(tmp_path, bad)
    got = watch_record.read(tmp_path)
    assert got.outcome is None and got.problem.startswith(f"{watch_record.RECORD} refused: ")
