"""Every output format decodes back to the logged values, bit for bit."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np
import pytest

from xrf_testing.log_cases import VARIABLES, columns_of, edge_rows, same_bits
from xrf_testing.writers import xrf2_bin, xrflog_segment
from xrflab.cli import main as xrf_main
from xrflab.logs import iter_csv_chunks, open_log
from xrflab.logs.convert import convert, matlab_names, variable_groups

CSV_TYPES = {
    "flag": np.uint8,
    "letter": np.uint8,
    "count": np.int32,
    "ratio": np.float32,
    "value": np.float64,
    "big": np.int64,
    "pos_left": np.float64,
    "pos_right": np.float64,
    "cycle_2": np.int64,
    "2 bad-name": np.int32,
}


def _expected(rows):
    want = columns_of(rows)
    want["flag"] = want["flag"].view(np.uint8)
    return want


def _same_or_both_nan(got: np.ndarray, want: np.ndarray) -> bool:
    """CSV text carries no NaN payload: a NaN reads back as NaN; every other value bit-exactly."""
    nan = np.isnan(want) if want.dtype.kind == "f" else np.zeros(len(want), bool)
    return bool(np.isnan(got[nan]).all()) and same_bits(got[~nan], want[~nan])


def test_csv_round_trip(edge_file: Path) -> None:
    out = convert(edge_file, "csv")
    assert out == edge_file.with_suffix(".csv")
    rows = list(csv.reader(io.StringIO(out.read_text())))
    head, body = rows[0], rows[1:]
    assert head == ["seq", "cycle", "t_ns", "t_s"] + list(CSV_TYPES)
    want = _expected(edge_rows())
    for j, name in enumerate(head[4:], start=4):
        text = [r[j] for r in body]
        t = CSV_TYPES[name]
        got = (
            np.array([t(float(x)) if np.issubdtype(t, np.floating) else int(x) for x in text], dtype=t)
            if np.issubdtype(t, np.floating)
            else np.array([int(x) for x in text], dtype=t)
        )
        assert _same_or_both_nan(got, want[name].astype(t, copy=False)), name
    assert [int(r[0]) for r in body] == list(range(len(body)))


def test_csv_float32_is_written_shortest_not_widened(edge_file: Path) -> None:
    text = convert(edge_file, "csv").read_text().splitlines()
    ratio = [line.split(",")[7] for line in text[1:]]
    assert "0.1" in ratio and "1e-45" in ratio  # float32 0.1 would be 0.10000000149011612 as double


def test_iter_csv_chunks_matches_the_file_and_streams(edge_file: Path) -> None:
    chunks = list(iter_csv_chunks(edge_file, chunk_rows=7))
    assert len(chunks) >= 64 // 7
    assert b"".join(chunks) == convert(edge_file, "csv").read_bytes()


def test_mat_round_trip(edge_file: Path) -> None:
    from scipy.io import loadmat

    out = convert(edge_file, "mat", edge_file.parent / "x.mat")
    mat = loadmat(out)
    want = _expected(edge_rows())
    names = dict(zip(CSV_TYPES, matlab_names(list(CSV_TYPES), reserved=("seq", "cycle", "t_ns", "t_s", "log_header"))))
    assert names["2 bad-name"] == "x2_bad_name" and names["cycle_2"] == "cycle_2"
    for name, mname in names.items():
        got = mat[mname].ravel()
        w = want[name]
        if name == "flag":
            got = got.astype(np.uint8)
        assert got.dtype.itemsize == w.dtype.itemsize and same_bits(got, w), name
    assert mat["seq"].dtype == np.uint64 and mat["seq"].ravel().tolist() == list(range(64))
    assert mat["t_ns"].dtype == np.int64
    assert '"cycle_freq": 1000' in str(mat["log_header"][0])


def test_seconds_from_the_start_in_every_table(tmp_path: Path) -> None:
    """CSV, MAT and Parquet carry t_s = (t_ns - the segment header's start_mono_ns) / 1e9 after
    t_ns, per segment; a variable called t_s keeps its values under t_s_2."""
    import pyarrow.parquet as pq
    from scipy.io import loadmat

    variables = [("t_s", 5), ("v", 3)]
    path = tmp_path / "secs.xrf"
    # two segments (an appending writer): the second run started 5 s later on the same clock
    path.write_bytes(
        xrflog_segment(variables, [(-1.0, i) for i in range(5)], t0=2_000_000_000)
        + xrflog_segment(variables, [(-2.0, i) for i in range(3)], t0=7_000_000_000, period_ns=250_000)
    )
    want = [(i + 10) * 1e-3 for i in range(5)] + [(i + 10) * 0.25e-3 for i in range(3)]

    rows = list(csv.reader(io.StringIO(convert(path, "csv").read_text())))
    assert rows[0] == ["seq", "cycle", "t_ns", "t_s", "t_s_2", "v"]
    assert [float(r[3]) for r in rows[1:]] == pytest.approx(want, abs=1e-12)
    assert [float(r[4]) for r in rows[1:]] == [-1.0] * 5 + [-2.0] * 3
    mat = loadmat(convert(path, "mat"))
    assert mat["t_s"].ravel().tolist() == pytest.approx(want, abs=1e-12) and mat["t_s"].dtype == np.float64
    table = pq.read_table(convert(path, "parquet"))
    assert table.column_names[:5] == ["seq", "cycle", "t_ns", "t_s", "t_s_2"]
    assert table.column("t_s").to_pylist() == pytest.approx(want, abs=1e-12)
    assert table.column("t_ns").to_pylist()[0] == 2_000_000_000 + 10 * 1_000_000  # the exact value stays


def test_parquet_round_trip_keeps_dtypes(edge_file: Path) -> None:
    import pyarrow.parquet as pq

    out = convert(edge_file, "parquet", chunk_rows=10)
    pf = pq.ParquetFile(out)
    assert pf.metadata.num_row_groups == 7
    table = pf.read()
    want = _expected(edge_rows())
    want["flag"] = want["flag"].view(bool)
    for name, w in want.items():
        got = table.column(name).to_numpy()
        assert got.dtype == w.dtype or (name == "letter" and got.dtype == np.uint8), name
        assert same_bits(got, w), name
    assert table.schema.field("seq").type == "uint64"
    assert table.schema.field("letter").metadata == {b"xrf_type": b"char"}
    assert b"xrflog.headers" in table.schema.metadata


def _rrd_scalars(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """entity path -> (cycle, value) read back with rerun's own RRD reader."""
    from rerun.chunk import RrdReader

    out: dict[str, list] = {}
    reader = RrdReader(path)
    assert reader.blueprints(), "the blueprint is stored in the file"
    for chunk in reader.stream():
        batch = chunk.to_record_batch()
        if "Scalars:scalars" not in batch.schema.names:
            continue
        entity = batch.schema.metadata[b"rerun:entity_path"].decode()
        cyc = batch.column("cycle").to_numpy()
        vals = np.array([v[0] for v in batch.column("Scalars:scalars").to_pylist()], dtype=np.float64)
        out.setdefault(entity, []).append((cyc, vals))
    result = {}
    for e, parts in out.items():
        cyc = np.concatenate([p[0] for p in parts])
        val = np.concatenate([p[1] for p in parts])
        order = np.argsort(cyc, kind="stable")
        result[e] = (cyc[order], val[order])
    return result


def test_rrd_round_trip(edge_file: Path) -> None:
    out = convert(edge_file, "rrd", chunk_rows=20)
    scalars = _rrd_scalars(out)
    want = _expected(edge_rows())
    assert "/log/pos/pos_left" in scalars and "/log/pos/pos_right" in scalars
    assert "/log/signals/value" in scalars
    for name, w in want.items():
        entity = [e for e in scalars if e.rsplit("/", 1)[-1] in (name, name.replace(" ", "\\ "))]
        assert len(entity) == 1, (name, list(scalars))
        cyc, got = scalars[entity[0]]
        assert cyc.tolist() == [s + 10 for s in range(64)]
        # rerun scalars are float64: exact for every type but int64 beyond 2**53.
        assert _same_or_both_nan(got, w.astype(np.float64)) or name in ("value",), name
        if name == "value":  # the NaN payload survives too: float64 passes through untouched
            assert same_bits(got, w)


def test_variable_groups() -> None:
    assert variable_groups(["pos_left", "pos_right", "x", "steer_left"]) == {
        "pos_left": "pos",
        "pos_right": "pos",
        "x": "signals",
        "steer_left": "signals",
    }


def test_matlab_names() -> None:
    assert matlab_names(["a b", "_x", "1", "a_b", "ok", "z" * 80]) == ["a_b", "x_x", "x1", "a_b_2", "ok", "z" * 63]


def test_two_segments_and_damage_convert(tmp_path: Path) -> None:
    rows = edge_rows(30)
    path = tmp_path / "two.xrf"
    path.write_bytes(xrflog_segment(VARIABLES, rows[:10]) + b"junk" + xrflog_segment(VARIABLES, rows[10:])[:-3])
    import pyarrow.parquet as pq

    table = pq.read_table(convert(path, "parquet"))
    assert table.num_rows == 29
    assert same_bits(table.column("big").to_numpy(), columns_of(rows)["big"][:29])


def test_segments_with_other_variables_refuse_to_merge(tmp_path: Path) -> None:
    path = tmp_path / "mixed.xrf"
    path.write_bytes(xrflog_segment([("x", 5)], [(1.0,)]) + xrflog_segment([("y", 3)], [(2,)]))
    log = open_log(path)
    assert [s.records.dtype.names[3] for s in log.segments] == ["x", "y"]
    with pytest.raises(ValueError, match="segment 1"):
        convert(path, "csv")
    assert not list(tmp_path.glob("*.part")) and not (tmp_path / "mixed.csv").exists()


def test_xrf2_bin_converts(tmp_path: Path) -> None:
    rows = [r[:6] for r in edge_rows(40)]
    path = tmp_path / "old.bin"
    path.write_bytes(xrf2_bin(VARIABLES[:6], rows))
    text = convert(path, "csv").read_text().splitlines()
    assert text[0] == "seq,flag,letter,count,ratio,value,big" and len(text) == 41
    from scipy.io import loadmat

    mat = loadmat(convert(path, "mat"))
    assert same_bits(mat["big"].ravel(), columns_of(edge_rows(40))["big"])
    scalars = _rrd_scalars(convert(path, "rrd"))
    assert scalars["/log/signals/count"][0].tolist() == list(range(40))


def test_empty_log_converts(tmp_path: Path) -> None:
    path = tmp_path / "empty.xrf"
    path.write_bytes(xrflog_segment(VARIABLES, []))
    assert convert(path, "csv").read_text().startswith("seq,cycle,t_ns,t_s,flag")
    import pyarrow.parquet as pq

    assert pq.read_table(convert(path, "parquet")).num_rows == 0
    convert(path, "mat")
    convert(path, "rrd")


def test_cli_decode(edge_file: Path, tmp_path: Path, capsys) -> None:
    assert xrf_main(["decode", str(edge_file), "--to", "parquet", "-o", str(tmp_path / "o.parquet")]) == 0
    capsys.readouterr()
    assert (tmp_path / "o.parquet").exists()
    assert xrf_main(["decode", str(edge_file)]) == 0
    assert Path(capsys.readouterr().out.strip()) == edge_file.with_suffix(".csv")
    bad = tmp_path / "bad.xrf"
    bad.write_bytes(xrflog_segment([("x", 5)], [(1.0,)]).replace(b'"type": 5', b'"type": 42'))
    assert xrf_main(["decode", str(bad)]) == 1
    assert "unknown type code 42" in capsys.readouterr().err


def test_a_log_of_no_records_is_converted_from_itself_not_reopened_by_path(tmp_path: Path) -> None:
    """Issue 26: the appliance hands the converter the LogFile it opened safely (a private copy
    of a file the loop may truncate); a LogFile of no records is falsy, and `log or open_log(path)`
    reopened - and mapped - the loop's file by its name, where a truncation killed the appliance."""
    empty = tmp_path / "empty.xrf"
    empty.write_bytes(xrflog_segment([("x", 5)], []))
    log = open_log(empty)
    assert len(log) == 0
    gone = tmp_path / "no-such-file.xrf"  # the name given: never opened
    assert b"x" in b"".join(iter_csv_chunks(gone, log=log))
    for fmt in ("csv", "parquet", "mat"):
        convert(gone, fmt, tmp_path / f"o.{fmt}", log=log)


def test_the_appliances_conversion_child(edge_file: Path, tmp_path: Path) -> None:
    """convert_in_child (the appliance's downloads) writes what convert() writes, reading only the
    descriptor it is handed; an unreadable log is LogFormatError, any other failure says why."""
    import os

    from xrflab.logs.convert_child import ConversionFailed, convert_in_child
    from xrflab.logs.reader import LogFormatError

    fd = os.open(edge_file, os.O_RDONLY)
    try:
        out = convert_in_child(fd, "/nowhere/shown.xrflog", "parquet", tmp_path / "child.parquet", None)
        want = convert(edge_file, "parquet", tmp_path / "here.parquet")
        assert out.read_bytes() == want.read_bytes()
        with pytest.raises(ConversionFailed, match="to mat failed: .*No such file or directory"):
            convert_in_child(fd, "shown.xrflog", "mat", tmp_path / "no-such-folder" / "x.mat", None)
    finally:
        os.close(fd)
    junk = tmp_path / "junk.bin"
    junk.write_bytes(b"not a log at all" * 10)
    fd = os.open(junk, os.O_RDONLY)
    try:
        with pytest.raises(LogFormatError):
            convert_in_child(fd, "junk.bin", "rrd", tmp_path / "junk.rrd", None)
    finally:
        os.close(fd)
