"""The run's parameter change table travels inside every download format (live tuning, issue 28;
docs/logging/decoding.md): CSV as a zip beside the samples, MAT as a struct, Parquet as key-value
metadata, .rrd as a text log on the cycle and time lines; the samples are unchanged."""

from __future__ import annotations

import csv
import io
import json
import zipfile
from pathlib import Path

import numpy as np

from xrf_testing.log_cases import VARIABLES
from xrf_testing.writers import xrflog_segment
from xrflab.logs import iter_csv_chunks
from xrflab.logs.convert import CHANGE_COLUMNS, CHANGES_ENTITY, CHANGES_META, convert, iter_csv_zip_chunks

CHANGES = [
    {"run": 7, "cycle": 20, "t": 1795000000.25, "name": "PID_Left\\Kp", "old": 1.0, "new": 2.5, "who": "ada"},
    {"run": 7, "cycle": 20, "t": 1795000000.25, "name": "PID_Left\\Ki", "old": 0.0, "new": 0.125, "who": "ada"},
    {"run": 7, "cycle": 41, "t": 1795000001.5, "name": "PID_Left\\Kp", "old": 2.5, "new": -3e-7, "who": 'bob, "x"'},
]


def test_csv_with_changes_is_a_zip_of_the_samples_and_the_changes(edge_file: Path, tmp_path: Path) -> None:
    plain = b"".join(iter_csv_chunks(edge_file))
    out = convert(edge_file, "csv", changes=CHANGES)
    assert out.suffix == ".zip"
    with zipfile.ZipFile(out) as z:
        names = z.namelist()
        assert names == [f"{edge_file.stem}.csv", "run7_param_changes.csv"]
        assert z.read(names[0]) == plain  # the samples: the same CSV as without changes
        rows = list(csv.DictReader(io.StringIO(z.read(names[1]).decode())))
    assert list(rows[0]) == list(CHANGE_COLUMNS)
    assert [(int(r["cycle"]), r["name"], float(r["old"]), float(r["new"]), r["who"]) for r in rows] == [
        (c["cycle"], c["name"], c["old"], c["new"], c["who"]) for c in CHANGES
    ]
    # Streamed in steps of the samples' chunks (the route's way), member names as asked.
    chunks = list(iter_csv_zip_chunks(edge_file, CHANGES, ("a.csv", "b.csv"), chunk_rows=10))
    with zipfile.ZipFile(io.BytesIO(b"".join(chunks))) as z:
        assert z.read("a.csv") == plain


def test_csv_without_changes_stays_plain(edge_file: Path) -> None:
    assert convert(edge_file, "csv", changes=[]).read_bytes() == b"".join(iter_csv_chunks(edge_file))


def test_mat_has_a_param_changes_struct(edge_file: Path) -> None:
    from scipy.io import loadmat

    m = loadmat(convert(edge_file, "mat", changes=CHANGES), simplify_cells=True)
    pc = m["param_changes"]
    assert list(np.atleast_1d(pc["cycle"])) == [20, 20, 41]
    assert list(pc["name"]) == [c["name"] for c in CHANGES]
    assert list(pc["who"]) == [c["who"] for c in CHANGES]
    assert np.array_equal(pc["old"], [1.0, 0.0, 2.5]) and np.array_equal(pc["new"], [2.5, 0.125, -3e-7])
    assert np.array_equal(pc["t"], [c["t"] for c in CHANGES])
    assert "count" in m  # the samples as before


def test_parquet_metadata_holds_the_changes(edge_file: Path, tmp_path: Path) -> None:
    import pyarrow.parquet as pq

    out = convert(edge_file, "parquet", changes=CHANGES)
    meta = pq.read_schema(out).metadata
    assert json.loads(meta[CHANGES_META.encode()]) == CHANGES
    assert pq.read_table(out).num_rows == 64
    # A log of no records still carries them.
    empty = tmp_path / "empty.xrf"
    empty.write_bytes(xrflog_segment(VARIABLES, []))
    got = pq.read_schema(convert(empty, "parquet", changes=CHANGES)).metadata
    assert json.loads(got[CHANGES_META.encode()]) == CHANGES


def test_rrd_has_a_text_log_entry_per_change(edge_file: Path) -> None:
    from rerun.chunk import RrdReader

    out = convert(edge_file, "rrd", changes=CHANGES)
    entries = []
    reader = RrdReader(out)
    views = [
        b.column("ViewBlueprint:class_identifier").to_pylist()
        for b in (c.to_record_batch() for c in reader.stream(store=reader.blueprints()[0]))
        if "ViewBlueprint:class_identifier" in b.schema.names
    ]
    assert [["TextLog"]] in views, views  # a text log view of the changes in the file's blueprint
    for chunk in reader.stream():
        batch = chunk.to_record_batch()
        entity = batch.schema.metadata[b"rerun:entity_path"].decode()
        if entity != "/" + CHANGES_ENTITY:
            continue
        text = [t[0] for t in batch.column("TextLog:text").to_pylist()]
        entries += zip(batch.column("cycle").to_numpy().tolist(), text, strict=True)
    assert sorted(entries) == [
        (20, "PID_Left\\Ki: 0 -> 0.125 at cycle 20 (ada)"),
        (20, "PID_Left\\Kp: 1 -> 2.5 at cycle 20 (ada)"),
        (41, 'PID_Left\\Kp: 2.5 -> -3e-07 at cycle 41 (bob, "x")'),
    ]
