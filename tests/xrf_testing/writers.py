"""Writers of the two log formats, written from the specs (not from the reader) to make fixtures.

`xrflog_segment` follows docs/logging/file-format.md byte for byte; `xrf2_bin` follows
XRF2_API.md ("XRF2's file format"). Both pack records with `struct`, independently of NumPy. The
magic and the header's dtype names are rt_core's (logformat.h): the reader's tests pin the magic's
bytes against the spec, and no second copy of either may exist (tests/logs/test_logformat.py).
"""

from __future__ import annotations

import json
import struct
from collections.abc import Sequence
from typing import Any

from xrflab.logs.logformat import MAGIC, VAR_TYPES

# code -> struct format character, size (XRF2_API.md's table): how this writer packs a value, an
# independent check of the reader's NumPy types (test_logformat.py compares the sizes with C's).
TYPES = {1: ("?", 1), 2: ("c", 1), 3: ("i", 4), 4: ("f", 4), 5: ("d", 8), 6: ("q", 8)}


def payload_format(codes: Sequence[int]) -> str:
    return "<" + "".join(TYPES[c][0] for c in codes)


def xrflog_segment(
    variables: Sequence[tuple[str, int]],
    rows: Sequence[Sequence[Any]],
    *,
    seqs: Sequence[int] | None = None,
    cycles: Sequence[int] | None = None,
    t0: int = 1_000_000_000,
    period_ns: int = 1_000_000,
    extra_header: dict | None = None,
    stride_pad: int = 0,
) -> bytes:
    """One segment: magic, J, S, JSON + padding, then one record per row."""
    codes = [c for _, c in variables]
    fmt = payload_format(codes)
    record_size = struct.calcsize(fmt)
    stride = (24 + record_size + 7) // 8 * 8 + stride_pad
    offsets, pos = [], 0
    for c in codes:
        offsets.append(pos)
        pos += TYPES[c][1]
    header = {
        "format": "xrflog",
        "version": 1,
        "program": "writer",
        "project": "",
        "build": "",
        "run": "",
        "pid": 1,
        "cycle_freq": 1000,
        "start_unix_ns": 1_795_000_000_000_000_000,
        "start_mono_ns": t0,
        "record_header": [["seq", "uint64"], ["cycle", "uint64"], ["t_ns", "int64"]],
        "record_size": record_size,
        "variables": [
            {"name": n, "type": c, "dtype": VAR_TYPES[c].header_dtype, "offset": o}
            for (n, c), o in zip(variables, offsets)
        ],
    }
    header.update(extra_header or {})
    js = (json.dumps(header) + "\n").encode()
    out = bytearray(MAGIC + struct.pack("<II", len(js), stride) + js)
    out += b"\0" * (-len(out) % 8)
    seqs = list(range(len(rows))) if seqs is None else list(seqs)
    cycles = [s + 10 for s in seqs] if cycles is None else list(cycles)
    for seq, cycle, row in zip(seqs, cycles, rows):
        rec = struct.pack("<QQq", seq, cycle, t0 + cycle * period_ns) + struct.pack(fmt, *row)
        out += rec + b"\0" * (stride - len(rec))
    return bytes(out)


def xrf2_bin(variables: Sequence[tuple[str, int]], rows: Sequence[Sequence[Any]]) -> bytes:
    """XRF2's .bin: names line, type-codes line, packed records (no padding, no header)."""
    fmt = payload_format([c for _, c in variables])
    out = bytearray(",".join(n for n, _ in variables).encode() + b"\n")
    out += ",".join(str(c) for _, c in variables).encode() + b"\n"
    for row in rows:
        out += struct.pack(fmt, *row)
    return bytes(out)
