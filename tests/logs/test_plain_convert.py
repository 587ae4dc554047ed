"""The light conversion child (logs/plain.py, issue 30 item 4): CSV and MAT of an undamaged log with
the standard library only, the same bytes as the NumPy path (Arrow's CSV, scipy's savemat), in a
child that loads no NumPy, pyarrow or scipy and stays small whatever the log's length."""

from __future__ import annotations

import io
import json
import os
import random
import struct
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from xrf_testing.convert_child import convert_in_child
from xrf_testing.log_cases import VARIABLES, edge_rows
from xrf_testing.writers import xrflog_segment
from xrflab.logs import plain
from xrflab.logs.convert import convert, iter_csv_chunks, iter_csv_zip_chunks

CHANGES: list[dict[str, Any]] = [
    {"run": 3, "cycle": 12, "t": 1795000000.25, "name": "kp", "old": 1.0, "new": 2.5, "who": "alice"},
    {"run": 3, "cycle": 40, "t": 1795000001.5, "name": "ki\u00e9", "old": 0, "new": -1e-9, "who": ""},
    {"run": 3, "cycle": 2**40, "t": 1795000002.0, "name": "a\0b", "old": -0.0, "new": 1e300, "who": "\0"},
]


def _edge_log(tmp_path: Path) -> Path:
    """Two segments (the second with its own start and a lost record), every type at its edges, a
    bool byte of 2, and a truncated last record."""
    rows = edge_rows(300)
    first = bytearray(xrflog_segment(VARIABLES, rows[:150]))
    second = xrflog_segment(
        VARIABLES,
        rows[150:],
        seqs=[i + 200 + (i > 50) for i in range(150)],
        t0=5_000_000_000,
        extra_header={"start_mono_ns": 4_000_000_000},
    )
    # The first record's bool (the payload's first byte, after seq, cycle, t_ns) written as 2.
    data_at = bytes(first).index(b"}\n") + 2
    data_at += -data_at % 8
    first[data_at + 24] = 2
    path = tmp_path / "edge.xrf"
    path.write_bytes(bytes(first) + second + b"\1\2\3")
    return path


def _plan(path: Path) -> plain.Plan:
    fd = os.open(path, os.O_RDONLY)
    p = plain.plan(path.name, fd)
    assert p is not None
    return p


def _child(log: Path, fmt: str, target: str, changes: list[dict[str, Any]] | None = None) -> tuple[bytes, list[str]]:
    out, mapped, peak_kb = convert_in_child(log, fmt, target, changes)
    return out, [mapped, str(peak_kb)]


def test_csv_is_arrows_byte_for_byte(tmp_path: Path) -> None:
    log = _edge_log(tmp_path)
    p = _plan(log)
    assert (p.count, p.lost, p.skipped) == (300, 1, 1)
    assert b"".join(plain.iter_csv(p)) == b"".join(iter_csv_chunks(log))


def test_csv_numbers_as_arrow_prints_them() -> None:
    """Random bit patterns and the decimal-exponent edges, float64 and float32, against Arrow."""
    import pyarrow as pa
    import pyarrow.csv as pcsv

    rng = random.Random(30)
    f64 = [struct.unpack("<d", rng.randbytes(8))[0] for _ in range(20000)]
    f64 += [s * 10.0**e * m for e in range(-12, 24) for m in (1.0, 1.5, 9.999999) for s in (1, -1)]
    f64 += [rng.uniform(-1e4, 1e4) for _ in range(5000)] + [0.0, -0.0, 2.0**53, 2.0**-1074]
    f32 = [struct.unpack("<f", rng.randbytes(4))[0] for _ in range(20000)]
    f32 += [struct.unpack("<f", struct.pack("<f", rng.uniform(-10, 10)))[0] for _ in range(5000)]
    f32 += [struct.unpack("<f", struct.pack("<f", x))[0] for x in f64[-250:] if abs(x) < 3e38]
    for values, dtype, text in ((f64, np.float64, plain.f64_text), (f32, np.float32, plain.f32_text)):
        sink = io.BytesIO()
        table = pa.table({"x": pa.array(np.array(values, dtype=dtype))})
        pcsv.write_csv(table, sink, write_options=pcsv.WriteOptions(include_header=False, quoting_style="needed"))
        want = sink.getvalue().decode().split("\n")[:-1]
        got = [text(v) for v in values]
        wrong = [(v, g, w) for v, g, w in zip(values, got, want) if g != w]
        assert not wrong, f"{dtype.__name__}: {len(wrong)} differ, e.g. {wrong[:5]}"


def test_mat_is_scipys_byte_for_byte(tmp_path: Path) -> None:
    """After the 128-byte file header (its text holds the time), with and without changes."""
    log = _edge_log(tmp_path)
    p = _plan(log)
    for changes in (None, CHANGES):
        want, got = tmp_path / "scipy.mat", tmp_path / "plain.mat"
        convert(log, "mat", want, changes=changes)
        with open(got, "wb") as f:
            plain.write_mat(p, f, changes)
        a, b = want.read_bytes(), got.read_bytes()
        assert b[:128].startswith(b"MATLAB 5.0 MAT-file Platform: posix, Created on: ")
        assert b[124:128] == a[124:128] == b"\x00\x01IM"
        assert b[128:] == a[128:]


def test_the_childs_mat_reads_back_in_scipy(tmp_path: Path) -> None:
    """The child's MAT, read by scipy.io.loadmat in this process: the values the NumPy path wrote."""
    from scipy.io import loadmat

    log = _edge_log(tmp_path)
    _child(log, "mat", str(tmp_path / "child.mat"), CHANGES)
    convert(log, "mat", tmp_path / "scipy.mat", changes=CHANGES)
    got, want = loadmat(tmp_path / "child.mat"), loadmat(tmp_path / "scipy.mat")
    names = [k for k in want if not k.startswith("__")]
    assert names == [k for k in got if not k.startswith("__")]
    assert {"seq", "t_s", "flag", "letter", "x2_bad_name", "log_header", "param_changes"} <= set(names)
    for name in names:
        if name == "param_changes":
            for field in ("cycle", "t", "old", "new"):
                assert got[name][field][0, 0].tobytes() == want[name][field][0, 0].tobytes(), field
            for field in ("name", "who"):
                assert [c.tolist() for c in got[name][field][0, 0].ravel()] == [
                    c.tolist() for c in want[name][field][0, 0].ravel()
                ]
            continue
        assert got[name].dtype == want[name].dtype and got[name].shape == want[name].shape, name
        assert got[name].tobytes() == want[name].tobytes(), name
    assert got["flag"][0, 0] == 2  # the bool byte as written: the NumPy path keeps it too
    assert got["seq"].shape == (300, 1)


def test_the_child_loads_no_numpy_arrow_or_scipy_and_stays_small(tmp_path: Path) -> None:
    """CSV (streamed, with and without changes) and MAT of a 35 MB log: nothing but the standard
    library and rt_core's binding mapped; the peak RSS is the interpreter's, not the log's (before:
    52-56 MB of imports, and more with the log)."""
    big = tmp_path / "400000.xrflog"
    big.write_bytes(
        xrflog_segment([(f"v{i}", 5) for i in range(8)], [[r * 0.5 + i for i in range(8)] for r in range(400_000)])
    )
    out, (mapped, peak_kb) = _child(big, "csv", "-")
    assert mapped == "[]"
    assert out.count(b"\n") == 400_000 + 2  # the counts line, the header, the rows
    assert int(peak_kb) < 30 * 1024, f"CSV child peak {int(peak_kb) / 1024:.1f} MB"
    out, (mapped, peak_kb) = _child(big, "csv", "-", CHANGES)
    assert mapped == "[]" and int(peak_kb) < 30 * 1024
    with zipfile.ZipFile(io.BytesIO(out.split(b"\n", 1)[1])) as z:
        assert z.namelist() == ["samples.csv", "changes.csv"]
        assert z.read("changes.csv").decode() == plain.changes_csv(CHANGES)
    _, (mapped, peak_kb) = _child(big, "mat", str(tmp_path / "big.mat"))
    assert mapped == "[]"
    assert int(peak_kb) < 30 * 1024, f"MAT child peak {int(peak_kb) / 1024:.1f} MB"
    assert (tmp_path / "big.mat").stat().st_size > 400_000 * 8 * 12


def test_a_csv_zip_with_changes_holds_the_same_members(tmp_path: Path) -> None:
    log = _edge_log(tmp_path)
    out, _ = _child(log, "csv", "-", CHANGES)
    counts, body = out.split(b"\n", 1)
    assert json.loads(counts) == {"skipped": 1, "lost": 1}
    want = b"".join(iter_csv_zip_chunks(log, CHANGES, ("samples.csv", "changes.csv")))
    with zipfile.ZipFile(io.BytesIO(body)) as got, zipfile.ZipFile(io.BytesIO(want)) as ref:
        assert got.namelist() == ref.namelist()
        for name in ref.namelist():
            assert got.read(name) == ref.read(name), name


@pytest.mark.parametrize("damage", ["garbage", "xrf2", "other_variables", "long_stride"])
def test_what_plain_does_not_read_goes_to_numpy(tmp_path: Path, damage: str) -> None:
    """Damage inside a segment, an XRF2 .bin, segments that differ, records longer than plain.py
    reads: plain.plan says no, and the child converts with the NumPy path, as before."""
    from xrf_testing.writers import xrf2_bin

    rows = edge_rows(40)
    log = tmp_path / "odd.xrf"
    if damage == "garbage":
        seg = xrflog_segment(VARIABLES, rows)
        log.write_bytes(seg[: len(seg) - 20 * 112] + b"\xff" * 37 + seg[len(seg) - 20 * 112 :])
    elif damage == "long_stride":  # records the writer made 70 KB long: plain.py reads none that long
        log.write_bytes(xrflog_segment(VARIABLES, rows, stride_pad=70_000))
    elif damage == "xrf2":
        log.write_bytes(xrf2_bin(VARIABLES, rows))
    else:
        log.write_bytes(xrflog_segment(VARIABLES, rows) + xrflog_segment([("other", 5)], [(1.0,)]))
    fd = os.open(log, os.O_RDONLY)
    try:
        assert plain.plan(log.name, fd) is None
    finally:
        os.close(fd)
    if damage == "other_variables":
        return  # the NumPy path refuses it (test_runs_logs: the 422 with its words)
    out, (mapped, _) = _child(log, "csv", "-")
    assert "numpy" in mapped
    assert out.split(b"\n", 1)[1] == b"".join(iter_csv_chunks(log))


def test_a_csv_of_many_float32_values_is_left_to_arrow(tmp_path: Path) -> None:
    """float32 text is a search over precisions here (~20x a double's time): past
    CSV_MAX_F32_VALUES a CSV goes to the NumPy path (Arrow, in C); MAT, and a small CSV, stay."""
    variables = [("a", 4), ("b", 4)]
    for rows, plain_csv in ((1_000, True), (plain.CSV_MAX_F32_VALUES // 2 + 1, False)):
        log = tmp_path / f"f32_{rows}.xrf"
        log.write_bytes(xrflog_segment(variables, [(i * 0.1, -i / 3) for i in range(rows)]))
        fd = os.open(log, os.O_RDONLY)
        try:
            p = plain.plan(log.name, fd)
            assert p is not None and plain.f32_values(p) == 2 * rows
            assert plain.convert(log.name, fd, "csv", str(tmp_path / "out.csv"), [], []) is plain_csv
            assert (tmp_path / "out.csv").exists() is plain_csv  # nothing written when it says no
            assert plain.convert(log.name, fd, "mat", str(tmp_path / "out.mat"), [], []) is True
        finally:
            os.close(fd)
        for out in ("out.csv", "out.mat"):
            (tmp_path / out).unlink(missing_ok=True)
