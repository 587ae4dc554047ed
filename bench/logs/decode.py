"""Decode benchmark: N records x 16 doubles to every format, against a per-record Python reader.

    .venv/bin/python bench/logs/decode.py [--records 1000000] [--dir /tmp/xrf-bench]

The file is written in the xrflog format (docs/logging/file-format.md) with NumPy; the baseline
is what one writes without this module: read the header, then struct.unpack each record and
append it to a list (the time to build those rows is the baseline "decode").
"""

from __future__ import annotations

import argparse
import json
import struct
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "appliance"))

from xrflab.logs import open_log  # noqa: E402
from xrflab.logs.convert import convert
from xrflab.logs.logformat import MAGIC  # noqa: E402

NVARS = 16


def write_file(path: Path, n: int) -> None:
    variables = [{"name": f"x{i:02d}", "type": 5, "dtype": "float64", "offset": 8 * i} for i in range(NVARS)]
    header = {
        "format": "xrflog",
        "version": 1,
        "program": "bench",
        "project": "",
        "build": "",
        "run": "",
        "pid": 0,
        "cycle_freq": 1000,
        "start_unix_ns": 0,
        "start_mono_ns": 0,
        "record_header": [["seq", "uint64"], ["cycle", "uint64"], ["t_ns", "int64"]],
        "record_size": 8 * NVARS,
        "variables": variables,
    }
    js = (json.dumps(header) + "\n").encode()
    stride = 24 + 8 * NVARS
    head = MAGIC + struct.pack("<II", len(js), stride) + js
    head += b"\0" * (-len(head) % 8)
    rec = np.zeros(n, dtype=[("seq", "<u8"), ("cycle", "<u8"), ("t_ns", "<i8"), ("x", "<f8", NVARS)])
    rec["seq"] = rec["cycle"] = np.arange(n)
    rec["t_ns"] = np.arange(n) * 1_000_000
    rec["x"] = np.random.default_rng(0).standard_normal((n, NVARS))
    with open(path, "wb") as f:
        f.write(head)
        f.write(rec.tobytes())


def python_reader(path: Path) -> list[tuple]:
    """The straightforward reader: struct.unpack per record."""
    with open(path, "rb") as f:
        raw = f.read()
    jlen, stride = struct.unpack_from("<II", raw, 8)
    header = json.loads(raw[16 : 16 + jlen])
    fmt = struct.Struct("<QQq" + "d" * len(header["variables"]))
    pos = (16 + jlen + 7) // 8 * 8
    rows = []
    while pos + stride <= len(raw):
        rows.append(fmt.unpack_from(raw, pos))
        pos += stride
    return rows


def python_csv(path: Path, out: Path) -> None:
    """The straightforward converter: the per-record reader, then csv.writer (repr: exact)."""
    import csv

    rows = python_reader(path)
    with open(out, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["seq", "cycle", "t_ns"] + [f"x{i:02d}" for i in range(NVARS)])
        w.writerows(rows)


def timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--records", type=int, default=1_000_000)
    ap.add_argument("--dir", type=Path, default=Path("/tmp/xrf-bench"))
    args = ap.parse_args()
    args.dir.mkdir(parents=True, exist_ok=True)
    path = args.dir / "bench.xrf"
    write_file(path, args.records)
    print(f"{args.records} records x {NVARS} doubles, {path.stat().st_size / 1e6:.0f} MB")
    base = timed(lambda: python_reader(path))
    print(f"{'per-record Python reader (struct)':36s} {base:8.3f} s")

    # NumPy decode: open + touch every value (a column sum), so nothing stays lazily unread.
    def numpy_read() -> None:
        rec = open_log(path).records
        for i in range(NVARS):
            float(rec[f"x{i:02d}"].sum())

    numpy_s = timed(numpy_read)
    print(
        f"{'NumPy reader (open + read all)':36s} {numpy_s:8.3f} s   {base / numpy_s:7.1f}x faster than the Python reader"
    )
    base_csv = timed(lambda: python_csv(path, args.dir / "baseline.csv"))
    print(f"{'Python reader + csv.writer (repr)':36s} {base_csv:8.3f} s")
    for fmt in ("csv", "mat", "parquet", "rrd"):
        s = timed(lambda fmt=fmt: convert(path, fmt, args.dir / f"bench.{fmt}"))
        size = (args.dir / f"bench.{fmt}").stat().st_size / 1e6
        vs = (
            f"{base_csv / s:5.1f}x faster than Python reader + csv.writer"
            if fmt == "csv"
            else f"{s / base:5.2f}x the Python reader's decode alone"
        )
        print(f"{'to ' + fmt:36s} {s:8.3f} s   {size:5.0f} MB   {vs}")


if __name__ == "__main__":
    main()
