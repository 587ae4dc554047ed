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

What rerun expects here is bound to its version: the constants under "rerun 0.41" below are the one
place of it, and tests/logs/test_rrd_file.py fails when the pinned SDK no longer reads this file as
it reads its own.

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
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

from .logformat import RECORD_HEADER, RECORD_HEADER_SIZE
from .plain import PlainSegment, Plan, _windows, plan

# ---- rerun 0.41 (rerun-sdk pinned in pyproject.toml) ---------------------------------------------
# The stream header's version (major, minor, patch, 0) and the store info's crate version bits
# (the same four bytes as a little-endian int), the chunk metadata's format version, and the names
# of the columns, archetypes and components a 0.41 viewer looks for.
RERUN_VERSION = (0, 41, 0)
SORBET_VERSION = "0.1.4"
ROW_ID = "rerun.controls.RowId"
TUID_EXTENSION = "rerun.datatypes.TUID"
APPLICATION_ID = "xrflab"
CHANGES_ENTITY = "params/changes"  # the text log of applied parameter sets (.rrd and the live stream)
_SCALARS = ("rerun.archetypes.Scalars", "Scalars:scalars", "rerun.components.Scalar")
_TEXT = ("rerun.archetypes.TextLog", "TextLog:text", "rerun.components.Text")
_LEVEL = ("rerun.archetypes.TextLog", "TextLog:level", "rerun.components.TextLogLevel")
_START = ("rerun.archetypes.RecordingInfo", "RecordingInfo:start_time", "rerun.components.Timestamp")
_BP = "rerun.blueprint.archetypes."
_BPC = "rerun.blueprint.components."
GRID = 4  # ContainerKind of a Grid
# Frame kinds, protobuf enums (rerun's log_msg.proto and common.proto)
_SET_STORE_INFO, _ARROW_MSG, _ACTIVATE = 1, 2, 3
_RECORDING, _BLUEPRINT = 1, 2
_PYTHON_SDK = 2
_COMPRESSION_NONE, _ARROW_IPC = 1, 1
# ---------------------------------------------------------------------------------------------------

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


_SHORT_ESCAPES = {"\t": "\\t", "\n": "\\n", "\r": "\\r"}


def escape_part(part: str) -> str:
    """An ASCII entity path part as rerun escapes it (rr.escape_entity_path_part; the test compares
    every ASCII character): letters, digits, `_`, `-`, `.` as they are, tab/newline/return as
    \\t \\n \\r, other printable characters behind a backslash, control characters as \\u{XXXX}."""
    out = []
    for ch in part:
        if ch.isascii() and (ch.isalnum() or ch in "_-."):
            out.append(ch)
        elif ch in _SHORT_ESCAPES:
            out.append(_SHORT_ESCAPES[ch])
        elif " " <= ch <= "~":
            out.append("\\" + ch)
        else:
            out.append(f"\\u{{{ord(ch):04X}}}")
    return "".join(out)


def entity_paths(names: list[str]) -> dict[str, str]:
    """name -> entity path `/log/<group>/<name>`, parts escaped (what the SDK makes of convert.py's)."""
    groups = variable_groups(names)
    return {n: f"/log/{escape_part(groups[n])}/{escape_part(n)}" for n in names}


# ---- protobuf (wire format: varints and length-delimited fields) ---------------------------------


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        low = n & 0x7F
        n >>= 7
        if n:
            out.append(low | 0x80)
        else:
            out.append(low)
            return bytes(out)


def _pb_int(field: int, n: int) -> bytes:
    return _varint(field << 3) + _varint(n)


def _pb_bytes(field: int, payload: bytes) -> bytes:
    return _varint(field << 3 | 2) + _varint(len(payload)) + payload


def _pb_tuid(field: int, tuid: tuple[int, int]) -> bytes:
    return _pb_bytes(field, b"\x09" + struct.pack("<Q", tuid[0]) + b"\x11" + struct.pack("<Q", tuid[1]))


def _store_id(kind: int, recording_id: str) -> bytes:
    return (
        _pb_int(1, kind)
        + _pb_bytes(2, recording_id.encode("utf-8", "surrogateescape"))
        + _pb_bytes(3, _pb_bytes(1, APPLICATION_ID.encode()))
    )


def _store_info(store_id: bytes) -> bytes:
    v = sys.version_info
    python = _pb_int(1, v.major) + _pb_int(2, v.minor) + _pb_int(3, v.micro)
    source = _pb_int(1, _PYTHON_SDK) + _pb_bytes(2, _pb_bytes(1, python))
    major, minor, patch = RERUN_VERSION
    bits = major | minor << 8 | patch << 16
    return _pb_bytes(2, store_id) + _pb_bytes(5, source) + _pb_bytes(6, _pb_int(1, bits))


# ---- flatbuffers, written front to back -------------------------------------------------------------
# A table is written as its vtable, then the table (its offset to the vtable, the inline fields,
# each aligned to its size), then what its offset fields point to, all after it: flatbuffers'
# offsets point forward. A writer takes the buffer and returns where its object starts.

Writer = Callable[[bytearray], int]
_SIZES = {"B": 1, "h": 2, "i": 4, "q": 8, "o": 4}


def _pad(buf: bytearray, n: int) -> None:
    buf.extend(bytes(-len(buf) % n))


def _table(*fields: tuple[int, str, Any]) -> Writer:
    """fields: (slot, struct code or "o" for an offset, value or writer)."""

    def write(buf: bytearray) -> int:
        nslots = max((f[0] for f in fields), default=-1) + 1
        _pad(buf, 2)
        vt = len(buf)
        buf.extend(bytes(4 + 2 * nslots))
        _pad(buf, 4)
        start = len(buf)
        buf.extend(struct.pack("<i", start - vt))
        at: dict[int, int] = {}
        for slot, code, value in sorted(fields, key=lambda f: -_SIZES[f[1]]):
            _pad(buf, _SIZES[code])
            at[slot] = len(buf)
            buf.extend(bytes(4) if code == "o" else struct.pack("<" + code, value))
        struct.pack_into("<HH", buf, vt, 4 + 2 * nslots, len(buf) - start)
        for slot, pos in at.items():
            struct.pack_into("<H", buf, vt + 4 + 2 * slot, pos - start)
        for slot, code, value in fields:
            if code == "o":
                child = value(buf)
                struct.pack_into("<I", buf, at[slot], child - at[slot])
        return start

    return write


def _string(text: str) -> Writer:
    def write(buf: bytearray) -> int:
        _pad(buf, 4)
        pos = len(buf)
        data = text.encode("utf-8", "surrogateescape")
        buf.extend(struct.pack("<I", len(data)) + data + b"\0")
        return pos

    return write


def _vector(items: list[Writer]) -> Writer:
    def write(buf: bytearray) -> int:
        _pad(buf, 4)
        pos = len(buf)
        buf.extend(struct.pack("<I", len(items)) + bytes(4 * len(items)))
        for i, item in enumerate(items):
            slot = pos + 4 + 4 * i
            struct.pack_into("<I", buf, slot, item(buf) - slot)
        return pos

    return write


def _structs(pairs: list[tuple[int, int]]) -> Writer:
    """A vector of Arrow's 16-byte structs (FieldNode, Buffer), its elements 8-aligned."""

    def write(buf: bytearray) -> int:
        while (len(buf) + 4) % 8:
            buf.append(0)
        pos = len(buf)
        buf.extend(struct.pack("<I", len(pairs)))
        for a, b in pairs:
            buf.extend(struct.pack("<qq", a, b))
        return pos

    return write


def _flatbuffer(root: Writer) -> bytes:
    buf = bytearray(4)
    struct.pack_into("<I", buf, 0, root(buf))
    _pad(buf, 8)
    return bytes(buf)


# ---- Arrow IPC (the columnar format's stream: Schema, RecordBatch, end of stream) -----------------

# Type union members (Schema.fbs) and their tables
_INT, _FLOAT, _UTF8, _TIMESTAMP, _LIST, _FIXED_BINARY, _FIXED_LIST = 2, 3, 5, 10, 12, 15, 16
_MESSAGE_SCHEMA, _MESSAGE_BATCH = 1, 3
_V5 = 4


class Field:
    """An Arrow field: its type (union member and table), children, metadata."""

    def __init__(
        self,
        name: str,
        type_id: int,
        type_fields: tuple[tuple[int, str, Any], ...] = (),
        children: tuple[Field, ...] = (),
        meta: dict[str, str] | None = None,
        nullable: bool = True,
    ) -> None:
        self.name, self.type_id, self.type_fields = name, type_id, type_fields
        self.children, self.meta, self.nullable = children, meta or {}, nullable

    def writer(self) -> Writer:
        return _table(
            (0, "o", _string(self.name)),
            (1, "B", int(self.nullable)),
            (2, "B", self.type_id),
            (3, "o", _table(*self.type_fields)),
            (5, "o", _vector([c.writer() for c in self.children])),
            (6, "o", _key_values(self.meta)),
        )


def _key_values(meta: dict[str, str]) -> Writer:
    return _vector([_table((0, "o", _string(k)), (1, "o", _string(v))) for k, v in meta.items()])


def _int(bits: int, signed: bool) -> tuple[tuple[int, str, Any], ...]:
    return ((0, "i", bits), (1, "B", int(signed)))


class Column:
    """A column of a chunk: its field, its array's nodes and buffers (depth first, as IPC wants)."""

    def __init__(self, field: Field, nodes: list[tuple[int, int]], buffers: list[bytes]) -> None:
        self.field, self.nodes, self.buffers = field, nodes, buffers


def _le(a: array) -> bytes:
    if sys.byteorder == "big":
        a = array(a.typecode, a)
        a.byteswap()
    return a.tobytes()


def _offsets(n: int) -> bytes:
    """A list column's offsets when every row holds one value."""
    return _le(array("i", range(n + 1)))


def _ipc_message(header_type: int, header: Writer, body_len: int) -> bytes:
    meta = _flatbuffer(
        _table((0, "h", _V5), (1, "B", header_type), (2, "o", header), (3, "q", body_len)),
    )
    return struct.pack("<Ii", 0xFFFFFFFF, len(meta)) + meta


def arrow_stream(columns: list[Column], rows: int, meta: dict[str, str]) -> list[bytes]:
    """The Arrow IPC stream of one record batch, as parts to write one after the other."""
    schema = _table(
        (0, "h", 0),  # little-endian
        (1, "o", _vector([c.field.writer() for c in columns])),
        (2, "o", _key_values(meta)),
    )
    nodes: list[tuple[int, int]] = []
    spans: list[tuple[int, int]] = []
    body: list[bytes] = []
    size = 0
    for c in columns:
        nodes += c.nodes
        for b in c.buffers:
            spans.append((size, len(b)))
            body.append(b)
            size += len(b)
            pad = -len(b) % 8
            if pad:
                body.append(bytes(pad))
                size += pad
    batch = _table((0, "q", rows), (1, "o", _structs(nodes)), (2, "o", _structs(spans)))
    return [
        _ipc_message(_MESSAGE_SCHEMA, schema, 0),
        _ipc_message(_MESSAGE_BATCH, batch, size),
        *body,
        struct.pack("<Ii", 0xFFFFFFFF, 0),
    ]


# ---- rerun's chunks ---------------------------------------------------------------------------------


class Tuids:
    """rerun's ids (row, chunk, store info): a time in ns and a counter from a random start, both
    big-endian in the RowId column, so ids made later sort after (the SDK makes them alike)."""

    def __init__(self) -> None:
        self.time_ns = time.time_ns()
        self.inc = int.from_bytes(os.urandom(8), "big") >> 2

    def next(self) -> tuple[int, int]:
        self.inc += 1
        return self.time_ns, self.inc

    def rows(self, n: int) -> bytes:
        """n row ids, 16 bytes each."""
        out = bytearray(16 * n)
        prefix = struct.pack(">Q", self.time_ns)
        for j in range(8):
            out[j::16] = bytes([prefix[j]]) * n
        counter = array("Q", range(self.inc + 1, self.inc + 1 + n))
        if sys.byteorder == "little":
            counter.byteswap()  # big-endian
        raw = counter.tobytes()
        for j in range(8):
            out[8 + j :: 16] = raw[j::8]
        self.inc += n
        return bytes(out)


def tuid_text(tuid: tuple[int, int]) -> str:
    return f"{tuid[0]:016X}{tuid[1]:016x}"


def _row_id_column(ids: bytes, n: int) -> Column:
    field = Field(
        ROW_ID,
        _FIXED_BINARY,
        ((0, "i", 16),),
        meta={
            "ARROW:extension:metadata": '{"namespace":"row"}',
            "ARROW:extension:name": TUID_EXTENSION,
            "rerun:is_sorted": "true",
            "rerun:kind": "control",
        },
        nullable=False,
    )
    return Column(field, [(n, 0)], [b"", ids])


def _sorted(values: array) -> bool:
    return all(map(operator.le, values[:-1], values[1:]))


def _index_column(name: str, timestamp: bool, values: array) -> Column:
    """An index (time line) column: int64 sequence or timestamp in ns."""
    meta = {"rerun:index_name": name}
    if _sorted(values):
        meta["rerun:is_sorted"] = "true"
    meta["rerun:kind"] = "index"
    kind = (_TIMESTAMP, ((0, "h", 3),)) if timestamp else (_INT, _int(64, True))
    return Column(Field(name, kind[0], kind[1], meta=meta), [(len(values), 0)], [b"", _le(values)])


def _component_meta(desc: tuple[str, str, str]) -> dict[str, str]:
    archetype, component, component_type = desc
    return {
        "rerun:archetype": archetype,
        "rerun:component": component,
        "rerun:component_type": component_type,
        "rerun:kind": "data",
    }


def _list_field(desc: tuple[str, str, str], item: Field) -> Field:
    return Field(desc[1], _LIST, children=(item,), meta=_component_meta(desc))


def _scalars_column(values: bytes, n: int) -> Column:
    """Scalars:scalars, a list of one float64 a row (`values`: n little-endian float64s)."""
    item = Field("item", _FLOAT, ((0, "h", 2),))
    return Column(_list_field(_SCALARS, item), [(n, 0), (n, 0)], [b"", _offsets(n), b"", values])


def _int64_list_column(desc: tuple[str, str, str], values: list[int]) -> Column:
    n = len(values)
    item = Field("item", _INT, _int(64, True))
    return Column(_list_field(desc, item), [(n, 0), (n, 0)], [b"", _offsets(n), b"", _le(array("q", values))])


def _view_columns(kind: str, name: str, origin: str) -> list[Any]:
    """A blueprint view's own row: its class, its name and its origin (the .rrd's and the live
    recording's, logs/rerun_sender.py)."""
    return [
        _text_list_column(_bp("ViewBlueprint", "class_identifier", "ViewClass"), [[kind]]),
        _text_list_column(
            ("rerun.blueprint.archetypes.ViewBlueprint", "ViewBlueprint:display_name", "rerun.components.Name"),
            [[name]],
        ),
        _text_list_column(_bp("ViewBlueprint", "space_origin", "ViewOrigin"), [[origin]]),
    ]


def _text_list_column(desc: tuple[str, str, str], rows: list[list[str]]) -> Column:
    """A list of strings a row."""
    outer = array("i", [0])
    inner = array("i", [0])
    data = bytearray()
    for row in rows:
        for text in row:
            data += text.encode("utf-8", "surrogateescape")
            inner.append(len(data))
        outer.append(len(inner) - 1)
    n, m = len(rows), len(inner) - 1
    item = Field("item", _UTF8)
    return Column(_list_field(desc, item), [(n, 0), (m, 0)], [b"", _le(outer), b"", _le(inner), bytes(data)])


def _uint8_list_column(desc: tuple[str, str, str], values: list[int]) -> Column:
    n = len(values)
    item = Field("item", _INT, _int(8, False))
    return Column(_list_field(desc, item), [(n, 0), (n, 0)], [b"", _offsets(n), b"", bytes(values)])


def _uuid_list_column(desc: tuple[str, str, str], ids: list[bytes]) -> Column:
    """A list of one 16-byte id a row (FixedSizeList of 16 uint8)."""
    n = len(ids)
    byte = Field("item", _INT, _int(8, False), nullable=False)
    item = Field("item", _FIXED_LIST, ((0, "i", 16),), children=(byte,))
    col = _list_field(desc, item)
    return Column(col, [(n, 0), (n, 0), (16 * n, 0)], [b"", _offsets(n), b"", b"", b"".join(ids)])


class RrdWriter:
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

    def store_info(self, store_id: bytes) -> None:
        self._frame(_SET_STORE_INFO, [_pb_tuid(1, self.tuids.next()) + _pb_bytes(2, _store_info(store_id))])

    def chunk(self, store_id: bytes, entity: str, columns: list[Column], rows: int, static: bool = False) -> None:
        chunk_id = self.tuids.next()
        meta = {
            "rerun:entity_path": entity,
            "rerun:id": "chunk_" + tuid_text(chunk_id),
            "sorbet:version": SORBET_VERSION,
        }
        payload = arrow_stream(columns, rows, meta)
        size = sum(map(len, payload))
        head = (
            _pb_bytes(1, store_id)
            + _pb_tuid(6, chunk_id)
            + _pb_int(2, _COMPRESSION_NONE)
            + _pb_int(3, size)
            + _pb_int(4, _ARROW_IPC)
            + _pb_int(7, int(static))
            + _varint(5 << 3 | 2)
            + _varint(size)
        )
        self._frame(_ARROW_MSG, [head, *payload])

    def activate(self, blueprint_id: bytes) -> None:
        self._frame(_ACTIVATE, [_pb_bytes(1, blueprint_id) + _pb_int(3, 1)])  # make_default, not make_active


# ---- the recording ------------------------------------------------------------------------------------


def _blueprint_indexes(now: int) -> list[Column]:
    """The blueprint's time lines, as the SDK sets them: `blueprint` 0 and `log_time` now."""
    return [_index_column("blueprint", False, array("q", [0])), _index_column("log_time", True, array("q", [now]))]


def write_blueprint(w: RrdWriter, names: list[str], tuned: bool) -> None:
    """logs/convert.py's rrd_blueprint as the SDK stores it: one TimeSeriesView per variable group
    (sorted), a TextLogView of the changes when there are any, all in one Grid as the root."""
    store = _store_id(_BLUEPRINT, f"rec_{uuid.uuid4().hex}")
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
        w.chunk(store, entity, [_row_id_column(ids, 1), *_blueprint_indexes(now), *columns], 1)

    for vid in view_ids:
        one_row(
            f"/view/{vid}/ViewContents",
            [_text_list_column(_bp("ViewContents", "query", "QueryExpression"), [["$origin/**"]])],
        )
    for (kind, name, origin), vid in zip(views, view_ids):
        one_row(f"/view/{vid}", _view_columns(kind, name, origin))
    one_row(
        f"/container/{container}",
        [
            _uint8_list_column(_bp("ContainerBlueprint", "container_kind", "ContainerKind"), [GRID]),
            _text_list_column(
                _bp("ContainerBlueprint", "contents", "IncludedContent"), [[f"view/{v}" for v in view_ids]]
            ),
        ],
    )
    one_row(
        "/viewport", [_uuid_list_column(_bp("ViewportBlueprint", "root_container", "RootContainer"), [container.bytes])]
    )
    w.activate(store)


def _bp(archetype: str, component: str, component_type: str) -> tuple[str, str, str]:
    return (_BP + archetype, f"{archetype}:{component}", _BPC + component_type)


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
    return _le(array("d", col))


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
    store = _store_id(_RECORDING, recording_id)
    w.store_info(store)
    ids = w.tuids.rows(1)
    w.chunk(
        store, "/__properties", [_row_id_column(ids, 1), _int64_list_column(_START, [time.time_ns()])], 1, static=True
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
            indexes = [_index_column("cycle", False, cycle), _index_column("time", True, wall)]
            for i, (name, vt) in enumerate(zip(names, seg.layout.types)):
                raw = _field_bytes(window, stride, RECORD_HEADER_SIZE + seg.layout.offsets[i], vt.size)
                values = _float64s(raw, vt.typestr)
                rows = _row_id_column(w.tuids.rows(n), n)
                w.chunk(store, paths[name], [rows, *indexes, _scalars_column(values, n)], n)
    if changes:
        n = len(changes)
        now = time.time_ns()
        cycles = array("q", [int(c["cycle"]) for c in changes])
        times = array("q", [int(round(1e9 * float(c["t"]))) for c in changes])
        columns = [
            _row_id_column(w.tuids.rows(n), n),
            _index_column("cycle", False, cycles),
            _index_column("log_time", True, array("q", [now] * n)),
            _index_column("time", True, times),
            _text_list_column(_LEVEL, [["INFO"]] * n),
            _text_list_column(_TEXT, [[change_text(c)] for c in changes]),
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
