"""The reader: bit-exact values, damage recovery with notes, clear errors."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from xrf_testing.log_cases import VARIABLES, columns_of, edge_rows, same_bits
from xrf_testing.writers import xrf2_bin, xrflog_segment
from xrflab.logs import LogFormatError, open_log
from xrflab.logs.reader import MAGIC


def test_all_types_decode_bit_exactly(edge_file: Path) -> None:
    log = open_log(edge_file)
    assert log.kind == "xrflog" and log.skipped == [] and log.lost == 0
    rec = log.records
    rows = edge_rows()
    assert len(rec) == len(rows)
    assert rec.dtype["seq"] == np.uint64 and rec.dtype["t_ns"] == np.int64
    assert rec.dtype["letter"] == np.dtype("S1") and rec.dtype["ratio"] == np.dtype("<f4")
    for name, want in columns_of(rows).items():
        got = rec[name]
        if got.dtype.kind == "S":
            got = np.ascontiguousarray(got).view(np.uint8)
        assert same_bits(got, want), name
    assert rec["seq"].tolist() == list(range(len(rows)))
    assert rec["cycle"].tolist() == [s + 10 for s in range(len(rows))]
    # The logged variable `cycle` is kept, renamed so it does not shadow the record header's.
    assert [v.name for v in log.variables][-2:] == ["cycle", "2 bad-name"]
    assert [v.field for v in log.variables][-2:] == ["cycle_2", "2 bad-name"]


def test_single_segment_is_a_view_of_the_file(edge_file: Path) -> None:
    rec = open_log(edge_file).records
    assert not rec.flags.owndata and rec.base is not None


def test_truncated_last_record_is_dropped_and_reported(tmp_path: Path) -> None:
    full = xrflog_segment(VARIABLES, edge_rows(10))
    stride = struct.unpack_from("<I", full, 12)[0]
    path = tmp_path / "cut.xrf"
    path.write_bytes(full[: -stride + 30])  # 30 bytes of the last record made it to disk
    log = open_log(path)
    assert len(log.records) == 9
    assert log.skipped_bytes == 30
    assert len(log.skipped) == 1 and "truncated last record" in log.skipped[0] and "30 bytes" in log.skipped[0]
    assert same_bits(log.records["count"], columns_of(edge_rows(10))["count"][:9])


def test_header_only_and_empty_files(tmp_path: Path) -> None:
    head = xrflog_segment(VARIABLES, [])
    (tmp_path / "h.xrf").write_bytes(head)
    log = open_log(tmp_path / "h.xrf")
    assert len(log.records) == 0 and len(log.segments) == 1 and log.skipped == []
    (tmp_path / "e.xrf").write_bytes(b"")
    with pytest.raises(LogFormatError, match="e.xrf"):
        open_log(tmp_path / "e.xrf")


def test_two_segments_concatenate_and_lost_counts_seq_gaps(tmp_path: Path) -> None:
    rows = edge_rows(20)
    first = xrflog_segment(VARIABLES, rows[:10], seqs=[0, 1, 2, 3, 4, 8, 9, 10, 11, 12])  # 3 lost
    second = xrflog_segment(VARIABLES, rows[10:])
    path = tmp_path / "two.xrf"
    path.write_bytes(first + second)
    log = open_log(path)
    assert [len(s.records) for s in log.segments] == [10, 10]
    assert log.lost == 3 and log.skipped == []
    assert same_bits(log.records["value"], columns_of(rows)["value"])
    assert log.segments[1].offset == len(first)


def test_truncated_segment_followed_by_a_new_one(tmp_path: Path) -> None:
    """A crash mid-record, then the next run appends: both segments decode."""
    rows = edge_rows(20)
    first = xrflog_segment(VARIABLES, rows[:10])
    second = xrflog_segment(VARIABLES, rows[10:])
    stride = struct.unpack_from("<I", first, 12)[0]
    (tmp_path / "f.xrf").write_bytes(first[: -stride + 11] + second)
    log = open_log(tmp_path / "f.xrf")
    assert [len(s.records) for s in log.segments] == [9, 10]
    assert any("11 bytes" in n for n in log.skipped)


def test_garbage_appended(tmp_path: Path) -> None:
    rows = edge_rows(30)
    data = xrflog_segment(VARIABLES, rows)
    path = tmp_path / "g.xrf"
    path.write_bytes(data + bytes(range(256)) * 3 + b"\x07" * 13)
    log = open_log(path)
    assert len(log.records) == 30
    assert log.skipped_bytes == 256 * 3 + 13
    assert same_bits(log.records["value"], columns_of(rows)["value"])


@pytest.mark.parametrize("garbage", [b"\xde\xad\xbe\xef" * 5 + b"!", b"\0" * 200, np.random.default_rng(1).bytes(999)])
def test_garbage_inserted_mid_segment_resyncs(tmp_path: Path, garbage: bytes) -> None:
    rows = edge_rows(40)
    data = xrflog_segment(VARIABLES, rows)
    stride = struct.unpack_from("<I", data, 12)[0]
    cut = len(data) - 25 * stride  # between records 14 and 15
    path = tmp_path / "ins.xrf"
    path.write_bytes(data[:cut] + garbage + data[cut:])
    log = open_log(path)
    assert len(log.records) == 40, log.skipped
    assert log.skipped_bytes == len(garbage)
    assert log.records["seq"].tolist() == list(range(40))
    assert same_bits(log.records["big"], columns_of(rows)["big"])


def test_garbage_overwriting_records_reports_loss(tmp_path: Path) -> None:
    rows = edge_rows(40)
    data = bytearray(xrflog_segment(VARIABLES, rows))
    stride = struct.unpack_from("<I", data, 12)[0]
    start = len(data) - 20 * stride + 5
    data[start : start + 2 * stride] = b"\xff" * (2 * stride)  # destroys records 20, 21 and 22
    (tmp_path / "o.xrf").write_bytes(bytes(data))
    log = open_log(tmp_path / "o.xrf")
    assert len(log.records) == 37 and log.lost == 3
    assert log.skipped_bytes == 3 * stride


def test_garbage_between_segments_and_before_the_first(tmp_path: Path) -> None:
    rows = edge_rows(20)
    a, b = xrflog_segment(VARIABLES, rows[:10]), xrflog_segment(VARIABLES, rows[10:])
    (tmp_path / "b.xrf").write_bytes(b"junk" * 7 + a + b"\x01" * 333 + b)
    log = open_log(tmp_path / "b.xrf")
    assert [len(s.records) for s in log.segments] == [10, 10]
    assert log.skipped_bytes == 28 + 333
    assert any("before the first segment magic" in n for n in log.skipped)


def test_damaged_magic_and_unparsable_json(tmp_path: Path) -> None:
    rows = edge_rows(30)
    a, b, c = (xrflog_segment(VARIABLES, rows[i : i + 10]) for i in (0, 10, 20))
    bad_json = bytearray(b)
    bad_json[16:18] = b"{{"  # the JSON starts at byte 16
    bad_magic = b"XRFL0G1\n" + a[8:]
    (tmp_path / "m.xrf").write_bytes(a + bytes(bad_json) + c)
    log = open_log(tmp_path / "m.xrf")
    assert [len(s.records) for s in log.segments] == [10, 10]
    assert same_bits(
        log.records["count"], np.concatenate([columns_of(rows)["count"][:10], columns_of(rows)["count"][20:]])
    )
    assert any("JSON header does not parse" in n and f"{len(b)} bytes" in n for n in log.skipped), log.skipped
    (tmp_path / "n.xrf").write_bytes(bad_magic + c)
    log = open_log(tmp_path / "n.xrf")
    assert [len(s.records) for s in log.segments] == [10]
    assert log.skipped_bytes == len(a)


def test_unknown_type_code_is_a_clear_error(tmp_path: Path) -> None:
    path = tmp_path / "t.xrf"
    path.write_bytes(xrflog_segment([("x", 5)], [(1.0,)]).replace(b'"type": 5', b'"type": 9'))
    with pytest.raises(LogFormatError, match=r"t\.xrf.*'x'.*unknown type code 9"):
        open_log(path)


def test_unknown_version_is_a_clear_error(tmp_path: Path) -> None:
    path = tmp_path / "v.xrf"
    path.write_bytes(xrflog_segment([("x", 5)], [(1.0,)], extra_header={"version": 2}))
    with pytest.raises(LogFormatError, match=r"v\.xrf.*version 2"):
        open_log(path)


def test_not_a_log_file(tmp_path: Path) -> None:
    (tmp_path / "x.txt").write_bytes(b"hello world, this is not a log\nfile at all\n")
    with pytest.raises(LogFormatError, match="x.txt"):
        open_log(tmp_path / "x.txt")


def test_xrf2_bin_decodes(tmp_path: Path) -> None:
    rows = [r[:6] for r in edge_rows(50)]
    variables = VARIABLES[:6]
    path = tmp_path / "relbot_261122_110955.bin"
    path.write_bytes(xrf2_bin(variables, rows) + b"\x01\x02\x03")  # and a partial record
    log = open_log(path)
    assert log.kind == "xrf2" and log.columns == ["seq", "flag", "letter", "count", "ratio", "value", "big"]
    assert len(log.records) == 50 and log.skipped_bytes == 3 and "truncated" in log.skipped[0]
    want = columns_of(edge_rows(50))
    for name in ("flag", "count", "ratio", "value", "big"):
        assert same_bits(log.records[name], want[name]), name
    assert same_bits(np.ascontiguousarray(log.records["letter"]).view(np.uint8), want["letter"])
    assert log.segments[0].column("seq").tolist() == list(range(50))


def test_xrf2_bin_with_trailing_separators_and_unknown_code(tmp_path: Path) -> None:
    path = tmp_path / "a.bin"
    path.write_bytes(b"x,y,\n5,3,\n" + struct.pack("<di", 1.5, 7))
    log = open_log(path)
    assert log.records["x"].tolist() == [1.5] and log.records["y"].tolist() == [7]
    path.write_bytes(b"x,y\n5,7\n" + struct.pack("<di", 1.5, 7))
    with pytest.raises(LogFormatError, match=r"a\.bin.*unknown type code 7"):
        open_log(path)


def test_magic_constant_matches_the_spec() -> None:
    assert MAGIC == bytes.fromhex("5852464C4F47310A")


def test_a_variable_name_that_is_not_text_is_written_out_and_every_format_takes_it(tmp_path: Path) -> None:
    """Issue 26: a file the loop wrote itself may name a variable with a lone surrogate (JSON
    ``\\udcff``); it becomes the text ``\\udcff``, so the listing's JSON and CSV, Parquet and rrd
    (all UTF-8) never fail on it."""
    from xrflab.logs.convert import convert

    path = tmp_path / "s.xrf"
    path.write_bytes(xrflog_segment([("ok", 5), ("bad\udcff", 5)], [(1.0, 2.0), (3.0, 4.0)]))
    log = open_log(path)
    assert [v.name for v in log.variables] == ["ok", "bad\\udcff"]
    for fmt in ("csv", "parquet", "mat"):
        convert(path, fmt, tmp_path / f"o.{fmt}")
    assert "bad\\udcff" in (tmp_path / "o.csv").read_text()
