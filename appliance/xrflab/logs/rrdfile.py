"""rerun's `.rrd` of an undamaged xrflog file with the standard library only: the light conversion
child's (logs/convert_child.py; issue 30 item 4).

The rerun SDK path (logs/convert.py ``_to_rrd``) makes the child import NumPy, pyarrow and the rerun
SDK: 90-118 MB RSS beside the appliance, the appliance's peak (bench/README.md, session 11). This
module writes the same recording itself (plain.py reads the records, a window at a time with
``os.pread``; each window becomes one chunk per variable, written out before the next is read):

- one stream (``RRF2``, uncompressed) of framed protobuf messages: the blueprint store (its store
  info, one Arrow chunk per blueprint entity, the activation command), then the recording store
  (store info, the recording's start time, one chunk per variable and window, the text log of
  parameter changes);
- each chunk an Arrow IPC stream (a Schema and a RecordBatch message, flatbuffers written here) with
  rerun's column metadata ("sorbet"): the row ids, the ``cycle`` and ``time`` index columns,
  ``Scalars:scalars`` as a list of float64;
- no RRD footer (the manifest rerun's own writer appends for random access: a second Arrow table of chunk
  statistics). rerun reads a stream without one (the viewer, ``rerun rrd print``/``compare``,
  ``RrdReader``); only ``rerun rrd verify`` asks for it unless given ``--check-footers false``
  (its schema hash is over arrow-rs's own serialisation of a schema: not something to repeat here).

Uncompressed (rerun's one compression, LZ4, is too slow in pure Python): the file is about twice the
SDK's (bench/README.md, session 12).

The encoding (protobuf, flatbuffers, Arrow IPC, rerun's columns and messages) is logs/rerun_wire.py's,
shared with the live recording's sender; tests/logs/test_rrd_file.py fails when the pinned SDK no
longer reads this file as it reads its own.

Only the logs plain.py reads (plan) with ASCII variable names (rerun's escaping of other characters
is Unicode-table work this module does not repeat); anything else is left to logs/convert.py:
``convert`` returns False before anything is written.
"""

from __future__ import annotations

import operator
import os
import re
import struct
import sys
import time
import uuid
from array import array
from pathlib import Path
from typing import Any, BinaryIO

from .logformat import RECORD_HEADER, RECORD_HEADER_SIZE
from .plain import PlainSegment, Plan, _windows, plan
from .rerun_wire import (
    BLUEPRINT,
    GRID,
    LEVEL,
    RECORDING,
    RERUN_VERSION,
    START_TIME,
    TEXT,
    Column,
    Messages,
    Tuids,
    bp,
    escape_part,
    index_column,
    int64_list_column,
    le_bytes,
    make_store_id,
    row_id_column,
    scalars_column,
    text_list_column,
    uint8_list_column,
    uuid_list_column,
    view_columns,
)

CHANGES_ENTITY = "params/changes"  # the text log of applied parameter sets (.rrd and the live stream)


# Records read at a time: one chunk per variable of at most this many records' bytes (a 600 000
# record log of 4 doubles: ~40 chunks a variable; the viewer merges small chunks itself).
WINDOW_BYTES = 1 << 20

_INT64 = 1 << 63


# ---- names (shared with logs/convert.py's SDK path) ------------------------------------------------


def change_text(c: dict[str, Any]) -> str:
    """One change as the rerun text log shows it."""
    return f"{c['name']}: {c['old']:g} -> {c['new']:g} at cycle {c['cycle']} ({c.get('who', '')})"


def variable_groups(names: list[str]) -> dict[str, str]:
    """name -> group: the part before the first `_` or `.` when two or more variables share it
    (pos_left, pos_right -> pos); every other variable goes to the group `signals`."""
    prefix = {n: re.split(r"[_.]", n, maxsplit=1)[0] if re.search(r"[_.]", n) else "" for n in names}
    counts: dict[str, int] = {}
    for p in prefix.values():
        if p:
            counts[p] = counts.get(p, 0) + 1
    return {n: p if p and counts[p] >= 2 else "signals" for n, p in prefix.items()}


def entity_paths(names: list[str]) -> dict[str, str]:
    """name -> entity path `/log/<group>/<name>`, parts escaped (what the SDK makes of convert.py's)."""
    groups = variable_groups(names)
    return {n: f"/log/{escape_part(groups[n])}/{escape_part(n)}" for n in names}


class RrdWriter(Messages):
    """The framed messages of one .rrd stream, written to `f` as they are made."""

    def __init__(self, f: BinaryIO) -> None:
        self.f = f
        self.tuids = Tuids()
        major, minor, patch = RERUN_VERSION
        # FourCC, version, options: no compression, protobuf messages (rerun's StreamHeader)
        f.write(b"RRF2" + bytes([major, minor, patch, 0]) + bytes([0, 2, 0, 0]))

    def _frame(self, kind: int, parts: list[bytes]) -> None:
        self.f.write(struct.pack("<QQ", kind, sum(map(len, parts))))
        for p in parts:
            self.f.write(p)


# ---- the recording ------------------------------------------------------------------------------------


def _index(name: str, timestamp: bool, values: array) -> Column:
    return index_column(name, timestamp, le_bytes(values), all(map(operator.le, values[:-1], values[1:])))


def _blueprint_indexes(now: int) -> list[Column]:
    """The blueprint's time lines, as the SDK sets them: `blueprint` 0 and `log_time` now."""
    return [_index("blueprint", False, array("q", [0])), _index("log_time", True, array("q", [now]))]


def write_blueprint(w: RrdWriter, names: list[str], tuned: bool) -> None:
    """logs/convert.py's rrd_blueprint as the SDK stores it: one TimeSeriesView per variable group
    (sorted), a TextLogView of the changes when there are any, all in one Grid as the root."""
    store = make_store_id(BLUEPRINT, f"rec_{uuid.uuid4().hex}")
    w.store_info(store)
    groups = sorted(set(variable_groups(names).values()))
    views = [("TimeSeries", g, "/log/" + escape_part(g)) for g in groups]
    if tuned:
        views.append(("TextLog", "parameter changes", "/" + CHANGES_ENTITY))
    view_ids = [uuid.uuid4() for _ in views]
    container = uuid.uuid4()
    now = time.time_ns()

    def one_row(entity: str, columns: list[Column]) -> None:
        ids = w.tuids.rows(1)
        w.chunk(store, entity, [row_id_column(ids, 1), *_blueprint_indexes(now), *columns], 1)

    for vid in view_ids:
        one_row(
            f"/view/{vid}/ViewContents",
            [text_list_column(bp("ViewContents", "query", "QueryExpression"), [["$origin/**"]])],
        )
    for (kind, name, origin), vid in zip(views, view_ids):
        one_row(f"/view/{vid}", view_columns(kind, name, origin))
    one_row(
        f"/container/{container}",
        [
            uint8_list_column(bp("ContainerBlueprint", "container_kind", "ContainerKind"), [GRID]),
            text_list_column(
                bp("ContainerBlueprint", "contents", "IncludedContent"), [[f"view/{v}" for v in view_ids]]
            ),
        ],
    )
    one_row(
        "/viewport", [uuid_list_column(bp("ViewportBlueprint", "root_container", "RootContainer"), [container.bytes])]
    )
    w.activate(store)


def _field_bytes(window: bytes, stride: int, offset: int, size: int) -> bytes:
    """One field of every record in `window`, packed (the log's little-endian bytes)."""
    out = bytearray(len(window) // stride * size)
    for j in range(size):
        out[j::size] = window[offset + j :: stride]
    return bytes(out)


def _float64s(raw: bytes, typestr: str) -> bytes:
    """A packed little-endian column as little-endian float64s, as NumPy's astype(float64) makes
    them: float64 untouched (NaN payloads too), the others converted in C."""
    if typestr == "<f8":
        return raw
    code = {"f4": "f", "i4": "i", "i8": "q", "u8": "Q", "b1": "B", "S1": "B", "u1": "B"}[typestr[1:]]
    col = array(code, raw)
    if sys.byteorder == "big":
        col.byteswap()
    return le_bytes(array("d", col))


def _int64s(raw: bytes) -> array:
    """Packed little-endian 64-bit integers as int64 (an unsigned value wraps, as NumPy's astype)."""
    col = array("q", raw)
    if sys.byteorder == "big":
        col.byteswap()
    return col


def _wall(t_ns: array, shift: int) -> array:
    """t_ns + shift in int64, wrapping as NumPy's (Segment.wall_ns)."""
    try:
        return array("q", map(shift.__add__, t_ns))
    except OverflowError:
        return array("q", [(t + shift + _INT64) % (1 << 64) - _INT64 for t in t_ns])


def _shift(seg: PlainSegment) -> int:
    h = seg.layout.header
    return int(h.get("start_unix_ns", 0)) - int(h.get("start_mono_ns", 0))


def write_recording(w: RrdWriter, p: Plan, recording_id: str, changes: list[dict[str, Any]]) -> None:
    store = make_store_id(RECORDING, recording_id)
    w.store_info(store)
    ids = w.tuids.rows(1)
    w.chunk(
        store, "/__properties", [row_id_column(ids, 1), int64_list_column(START_TIME, [time.time_ns()])], 1, static=True
    )
    names = list(p.first.fields)
    paths = entity_paths(names)
    head = {n: (off, int(t[2:])) for n, t, off in RECORD_HEADER}
    for seg in p.segments:
        stride, shift = seg.layout.stride, _shift(seg)
        for window in _windows(p.fd, seg.layout.data, seg.count, stride, WINDOW_BYTES):
            n = len(window) // stride
            cycle = _int64s(_field_bytes(window, stride, *head["cycle"]))
            wall = _wall(_int64s(_field_bytes(window, stride, *head["t_ns"])), shift)
            indexes = [_index("cycle", False, cycle), _index("time", True, wall)]
            for i, (name, vt) in enumerate(zip(names, seg.layout.types)):
                raw = _field_bytes(window, stride, RECORD_HEADER_SIZE + seg.layout.offsets[i], vt.size)
                values = _float64s(raw, vt.typestr)
                rows = row_id_column(w.tuids.rows(n), n)
                w.chunk(store, paths[name], [rows, *indexes, scalars_column(values, n)], n)
    if changes:
        n = len(changes)
        now = time.time_ns()
        cycles = array("q", [int(c["cycle"]) for c in changes])
        times = array("q", [int(round(1e9 * float(c["t"]))) for c in changes])
        columns = [
            row_id_column(w.tuids.rows(n), n),
            _index("cycle", False, cycles),
            _index("log_time", True, array("q", [now] * n)),
            _index("time", True, times),
            text_list_column(LEVEL, [["INFO"]] * n),
            text_list_column(TEXT, [[change_text(c)] for c in changes]),
        ]
        w.chunk(store, "/" + CHANGES_ENTITY, columns, n)


def writable(p: Plan, changes: list[dict[str, Any]]) -> bool:
    """Whether this module writes what the SDK would for this log and these changes."""
    if not all(name.isascii() for name in p.first.fields):
        return False  # rerun escapes other characters by Unicode tables: the SDK does them
    for seg in p.segments:
        try:
            shift = _shift(seg)
        except (TypeError, ValueError):
            return False
        if not -_INT64 <= shift < _INT64:
            return False
    for c in changes:
        try:
            t, cycle = float(c["t"]), int(c["cycle"])
            change_text(c)
        except (KeyError, TypeError, ValueError):
            return False
        if not (abs(t) <= 1e11 and -_INT64 <= cycle < _INT64):
            return False  # the SDK refuses a time in ms, NumPy a cycle beyond int64: theirs to say
    return True


def write_rrd(p: Plan, f: BinaryIO, recording_id: str, changes: list[dict[str, Any]]) -> None:
    """The blueprint store, then the recording (the order the SDK writes them in)."""
    w = RrdWriter(f)
    write_blueprint(w, list(p.first.fields), tuned=bool(changes))
    write_recording(w, p, recording_id, changes)


def convert(shown: str, fd: int, target: str, changes: list[dict[str, Any]]) -> bool:
    """Write the log open as `fd` as .rrd to `target`, or return False, having written nothing,
    when the log is not one this module writes (logs/convert.py then does)."""
    p = plan(shown, fd)
    if p is None or not p.segments or not writable(p, changes):
        return False
    dest = Path(target)
    tmp = dest.with_name(f".{dest.name}.{os.getpid()}.part")
    try:
        with open(tmp, "wb") as f:
            write_rrd(p, f, Path(shown).name, changes)
        os.replace(tmp, dest)
    finally:
        if tmp.exists():
            tmp.unlink()
    return True
