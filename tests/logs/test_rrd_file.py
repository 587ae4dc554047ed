"""The light child's `.rrd` (logs/rrdfile.py, issue 30 item 4): written with the standard library
only, read by the pinned rerun (its CLI and its Python reader) as the same recording the SDK path
(logs/convert.py _to_rrd) writes, in a child that maps no NumPy, Arrow or rerun and stays small
whatever the log's length. When rerun changes its encoding, these fail: rrdfile.py's "rerun 0.41"
constants are where to look."""

from __future__ import annotations

import subprocess
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from xrf_testing.convert_child import convert_in_child
from xrf_testing.log_cases import VARIABLES, edge_rows
from xrf_testing.writers import xrf2_bin, xrflog_segment
from xrflab.logs import rerun_wire
from xrflab.logs.convert import convert

RERUN = Path(sys.executable).with_name("rerun")

CHANGES: list[dict[str, Any]] = [
    {"run": 3, "cycle": 12, "t": 1795000000.25, "name": "kp", "old": 1.0, "new": 2.5, "who": "alice"},
    {"run": 3, "cycle": 40, "t": 1795000001.5, "name": "ki\u00e9", "old": 0, "new": -1e-9, "who": ""},
]


def _two_segments(tmp_path: Path) -> Path:
    """Every type at its edges, two segments (the second with its own clock and a lost record), a
    truncated last record."""
    rows = edge_rows(300)
    second = xrflog_segment(
        VARIABLES,
        rows[150:],
        seqs=[i + 200 + (i > 50) for i in range(150)],
        t0=5_000_000_000,
        extra_header={"start_mono_ns": 4_000_000_000, "start_unix_ns": 1_700_000_000_000_000_000},
    )
    path = tmp_path / "edge.xrf"
    path.write_bytes(xrflog_segment(VARIABLES, rows[:150]) + second + b"\1\2\3")
    return path


def _ours(log: Path, out: Path, changes: list[dict[str, Any]] | None = None) -> tuple[str, int]:
    """The child's .rrd (the appliance's way: convert_child with the log as a descriptor)."""
    _, mapped, peak_kb = convert_in_child(log, "rrd", str(out), changes)
    return mapped, peak_kb


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(RERUN), "rrd", *args], capture_output=True, text=True, check=False)


def _same_recording(sdk: Path, ours: Path, chunk_by_chunk: bool = False) -> None:
    assert ours.read_bytes()[8] == 0 and sdk.read_bytes()[8] == 1, "ours uncompressed, the SDK's LZ4"
    verify = _cli("verify", "--check-footers", "false", str(ours))
    assert verify.returncode == 0, verify.stderr
    # Every entity's cycles, times and values, to the bit, and the text log, through rerun's reader.
    assert _scalars(ours) == _scalars(sdk)
    assert _text_log(ours) == _text_log(sdk)
    if chunk_by_chunk:
        # rerun's own comparison, chunk by chunk (log_time, the moment of writing, left out): only
        # where both files cut the log into the same chunks and hold no NaN (rerun's compare finds
        # a NaN unequal to itself: the SDK's file against itself fails).
        compare = _cli("compare", "--unordered", str(sdk), str(ours))
        assert compare.returncode == 0, compare.stderr[-3000:]


def _reader(path: Path) -> Any:
    from rerun.chunk import RrdReader

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # ours has no footer: rerun says it scans the file
        return RrdReader(path)


def _scalars(path: Path) -> dict[str, tuple[list[int], list[int], bytes]]:
    """entity -> (cycles, times, the float64 values' bytes), in row order, from rerun's reader."""
    out: dict[str, tuple[list[int], list[int], bytes]] = {}
    reader = _reader(path)
    for chunk in reader.stream(store=reader.recordings()[0]):
        batch = chunk.to_record_batch()
        if "Scalars:scalars" not in batch.schema.names:
            continue
        entity = batch.schema.metadata[b"rerun:entity_path"].decode()
        cyc, t, v = out.setdefault(entity, ([], [], b""))
        cyc += batch.column("cycle").cast("int64").to_pylist()
        t += batch.column("time").cast("int64").to_pylist()
        values = batch.column("Scalars:scalars").flatten().to_numpy().astype("<f8").tobytes()
        out[entity] = (cyc, t, v + values)
    return out


def _text_log(path: Path) -> list[tuple[Any, ...]]:
    reader = _reader(path)
    rows: list[tuple[Any, ...]] = []
    for chunk in reader.stream(store=reader.recordings()[0]):
        batch = chunk.to_record_batch()
        if "TextLog:text" in batch.schema.names:
            entity = batch.schema.metadata[b"rerun:entity_path"].decode()
            cols = ["cycle", "time", "TextLog:text", "TextLog:level"]
            values = [batch.column(c).cast("int64") if c == "time" else batch.column(c) for c in cols]
            rows += [(entity, *r) for r in zip(*(v.to_pylist() for v in values))]
    return rows


def _blueprint(path: Path) -> Any:
    """The blueprint as a tree, its random ids replaced by what they point to."""
    reader = _reader(path)
    entities: dict[str, dict[str, Any]] = {}
    for chunk in reader.stream(store=reader.blueprints()[0]):
        batch = chunk.to_record_batch()
        entity = batch.schema.metadata[b"rerun:entity_path"].decode()
        row = {n: batch.column(n).to_pylist()[-1] for n in batch.schema.names if ":" in n}
        entities.setdefault(entity, {}).update(row)
    root = bytes(entities["/viewport"]["ViewportBlueprint:root_container"][0])
    import uuid

    container = entities[f"/container/{uuid.UUID(bytes=root)}"]

    def view(ref: str) -> tuple[Any, ...]:
        v = entities["/" + ref]
        return (
            v["ViewBlueprint:class_identifier"],
            v["ViewBlueprint:display_name"],
            v["ViewBlueprint:space_origin"],
            entities[f"/{ref}/ViewContents"]["ViewContents:query"],
        )

    views = [view(ref) for ref in container["ContainerBlueprint:contents"]]
    return container["ContainerBlueprint:container_kind"], views, len(entities)


def _compare(
    tmp_path: Path, log: Path, changes: list[dict[str, Any]] | None = None, chunk_by_chunk: bool = False
) -> Path:
    sdk = convert(log, "rrd", tmp_path / "sdk.rrd", changes=changes)
    ours = tmp_path / "ours.rrd"
    mapped, _ = _ours(log, ours, changes)
    assert mapped == "[]", "the light child wrote it"
    _same_recording(sdk, ours, chunk_by_chunk)
    assert _blueprint(ours) == _blueprint(sdk)
    return ours


def test_every_type_two_segments_and_changes_read_back_as_the_sdks(tmp_path: Path) -> None:
    log = _two_segments(tmp_path)
    ours = _compare(tmp_path, log, CHANGES)
    got, want = _scalars(ours), _scalars(tmp_path / "sdk.rrd")
    assert sorted(got) == sorted(want) and "/log/signals/2\\ bad-name" in got
    for entity in want:
        assert got[entity] == want[entity], entity  # cycles, times, values to the bit (NaN payloads)
    assert [r[0] for r in _text_log(ours)] == ["/params/changes"] * 2
    cyc, times, _ = got["/log/signals/value"]
    assert len(cyc) == 300 and times[150] - times[149] != 1_000_000  # the second segment's own clock
    kind, views, _ = _blueprint(ours)
    assert kind == [4] and [v[1] for v in views] == [["pos"], ["signals"], ["parameter changes"]]


def test_without_changes_and_one_variable_group(tmp_path: Path) -> None:
    log = tmp_path / "one.xrf"
    log.write_bytes(xrflog_segment([("a_x", 5), ("a_y", 3)], [(i / 3, i) for i in range(1000)]))
    ours = _compare(tmp_path, log, chunk_by_chunk=True)
    assert [v[1] for v in _blueprint(ours)[1]] == [["a"]]


def test_an_empty_log(tmp_path: Path) -> None:
    log = tmp_path / "empty.xrf"
    log.write_bytes(xrflog_segment(VARIABLES, []))
    ours = _compare(tmp_path, log, CHANGES, chunk_by_chunk=True)
    assert _scalars(ours) == {} and len(_text_log(ours)) == 2


def test_a_big_log(tmp_path: Path) -> None:
    """300 000 records of three variables: many chunks a variable, the same recording."""
    n = 300_000
    log = tmp_path / "big.xrf"
    log.write_bytes(xrflog_segment([("x", 5), ("y", 4), ("k", 3)], [(i * 0.25, i / 7, i) for i in range(n)]))
    ours = _compare(tmp_path, log)
    cyc, _, values = _scalars(ours)["/log/signals/x"]
    assert len(cyc) == n and np.frombuffer(values, "<f8")[-1] == (n - 1) * 0.25


def test_the_child_maps_no_numpy_arrow_or_rerun_and_stays_small(tmp_path: Path) -> None:
    """A 35 MB log: nothing but the standard library and rt_core's binding mapped, the peak the
    interpreter's, not the log's (before: 90-118 MB, NumPy + pyarrow + the rerun SDK)."""
    big = tmp_path / "400000.xrflog"
    big.write_bytes(
        xrflog_segment([(f"v{i}", 5) for i in range(8)], [[r * 0.5 + i for i in range(8)] for r in range(400_000)])
    )
    assert big.stat().st_size > 35e6
    mapped, peak_kb = _ours(big, tmp_path / "big.rrd", CHANGES)
    assert mapped == "[]"
    assert peak_kb < 35 * 1024, f".rrd child peak {peak_kb / 1024:.1f} MB"
    assert (tmp_path / "big.rrd").stat().st_size > 400_000 * 8 * 8


@pytest.mark.parametrize("case", ["garbage", "xrf2", "non_ascii_name"])
def test_what_rrdfile_does_not_write_goes_to_the_sdk(tmp_path: Path, case: str) -> None:
    """Damage, an XRF2 .bin, a name rerun escapes by Unicode tables: the child writes the SDK's
    file, as before (LZ4-compressed: the SDK's, not ours)."""
    rows = edge_rows(40)
    log = tmp_path / "odd.xrf"
    if case == "garbage":
        seg = xrflog_segment(VARIABLES, rows)
        log.write_bytes(seg[: len(seg) - 20 * 112] + b"\xff" * 37 + seg[len(seg) - 20 * 112 :])
    elif case == "xrf2":
        log.write_bytes(xrf2_bin(VARIABLES, rows))
    else:
        log.write_bytes(xrflog_segment([("temp\u00e9rature", 5)], [(1.0,), (2.0,)]))
    out = tmp_path / "odd.rrd"
    mapped, _ = _ours(log, out)
    assert "numpy" in mapped and out.read_bytes()[8] == 1
    assert _cli("verify", str(out)).returncode == 0


def test_entity_path_escaping_is_reruns() -> None:
    import rerun as rr

    for c in map(chr, range(128)):
        name = f"a{c}b"
        assert rerun_wire.escape_part(name) == rr.escape_entity_path_part(name), repr(c)


def test_a_flatbuffer_reads_back_in_arrow() -> None:
    """The Arrow IPC stream of a chunk, read by pyarrow: types, metadata, values."""
    import pyarrow as pa

    w = rerun_wire.Tuids()
    n = 3
    values = np.array([1.5, -0.0, np.nan]).astype("<f8").tobytes()
    pairs = np.array([[1.0, 2.0], [3.0, 4.0], [5.0, -6.0]]).astype("<f8")
    cols = [
        rerun_wire.row_id_column(w.rows(n), n),
        rerun_wire.index_column("cycle", False, np.array([1, 2, 2], dtype="<i8").tobytes(), True),
        rerun_wire.index_column("time", True, np.array([5, 4, 6], dtype="<i8").tobytes(), False),
        rerun_wire.scalars_column(values, n),
    ]
    stream = b"".join(rerun_wire.arrow_stream(cols, n, {"k": "v"}))
    table = pa.ipc.open_stream(stream).read_all()
    assert table.schema.metadata == {b"k": b"v"}
    assert table.schema.field("time").type == pa.timestamp("ns")
    assert table.column("cycle").to_pylist() == [1, 2, 2]
    assert b"rerun:is_sorted" in table.schema.field("cycle").metadata
    assert b"rerun:is_sorted" not in table.schema.field("time").metadata  # 5, 4, 6: not sorted
    assert table.column("Scalars:scalars").combine_chunks().flatten().to_numpy().tobytes() == values
    # several series a row (the live recording's): a list of that many values a row
    two = pa.ipc.open_stream(
        b"".join(rerun_wire.arrow_stream([rerun_wire.scalars_column(pairs.tobytes(), n, 2)], n, {}))
    )
    assert two.read_all().column("Scalars:scalars").to_pylist() == pairs.tolist()
    ids = table.column(rerun_wire.ROW_ID).to_pylist()
    assert ids == sorted(ids) and len(set(ids)) == n
