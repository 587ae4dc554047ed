"""rerun 0.41's messages written with the standard library: protobuf, flatbuffers, Arrow IPC and
rerun's chunk columns (issue 30 item 4: neither the appliance nor its conversion child imports the
rerun SDK or pyarrow). One definition for the two streams made of them: a log's `.rrd` download
(logs/rrdfile.py) and a run's live recording sent to its proxy (logs/rerun_sender.py).

- protobuf: varints and length-delimited fields, rerun's store ids and store info;
- flatbuffers, written front to back (Arrow IPC's Schema and RecordBatch headers);
- Arrow IPC: a field (`Field`), a column (`Column`: its nodes and buffers, depth first), one record
  batch's stream (`arrow_stream`);
- rerun's chunks: row ids (`Tuids`), index and component columns with rerun's column metadata
  ("sorbet"), and `Messages`, the store info / chunk / blueprint activation messages a stream holds.

What rerun expects here is bound to its version: the constants under "rerun 0.41" below are the one
place of it; tests/logs/test_rrd_file.py and tests/logs/test_live_sender.py fail when the pinned SDK
no longer reads what these make as it reads its own.
"""

from __future__ import annotations

import os
import struct
import sys
import time
from array import array
from collections.abc import Callable
from typing import Any

# ---- rerun 0.41 (rerun-sdk pinned in pyproject.toml) ---------------------------------------------
# The stream header's version (major, minor, patch, 0) and the store info's crate version bits
# (the same four bytes as a little-endian int), the chunk metadata's format version, and the names
# of the columns, archetypes and components a 0.41 viewer looks for.
RERUN_VERSION = (0, 41, 0)
SORBET_VERSION = "0.1.4"
ROW_ID = "rerun.controls.RowId"
TUID_EXTENSION = "rerun.datatypes.TUID"
APPLICATION_ID = "xrflab"
SCALARS = ("rerun.archetypes.Scalars", "Scalars:scalars", "rerun.components.Scalar")
TEXT = ("rerun.archetypes.TextLog", "TextLog:text", "rerun.components.Text")
LEVEL = ("rerun.archetypes.TextLog", "TextLog:level", "rerun.components.TextLogLevel")
START_TIME = ("rerun.archetypes.RecordingInfo", "RecordingInfo:start_time", "rerun.components.Timestamp")
_BP = "rerun.blueprint.archetypes."
_BPC = "rerun.blueprint.components."
GRID = 4  # ContainerKind of a Grid
# Frame kinds, protobuf enums (rerun's log_msg.proto and common.proto)
SET_STORE_INFO, ARROW_MSG, ACTIVATE = 1, 2, 3
RECORDING, BLUEPRINT = 1, 2
_PYTHON_SDK = 2
_COMPRESSION_NONE, _ARROW_IPC = 1, 1
# ---------------------------------------------------------------------------------------------------


_SHORT_ESCAPES = {"\t": "\\t", "\n": "\\n", "\r": "\\r"}


def escape_part(part: str) -> str:
    """An entity path part as rr.escape_entity_path_part writes it (tests/logs/test_rrd_file.py
    compares every ASCII character): letters, digits, `_`, `-`, `.` as they are, tab/newline/return
    as \\t \\n \\r, other printable ASCII behind a backslash, control characters as \\u{XXXX}; a
    letter or digit beyond ASCII as it is (rerun's `char::is_alphanumeric`; where Python's Unicode
    tables say otherwise, as \\u{XXXX}, which rerun reads as the same character: the path is the
    same, only its text differs, which is why logs/rrdfile.py leaves non-ASCII names to the SDK)."""
    out = []
    for ch in part:
        if ch.isalnum() or ch in "_-.":
            out.append(ch)
        elif ch in _SHORT_ESCAPES:
            out.append(_SHORT_ESCAPES[ch])
        elif " " <= ch <= "~":
            out.append("\\" + ch)
        else:
            out.append(f"\\u{{{ord(ch):04X}}}")
    return "".join(out)


def bp(archetype: str, component: str, component_type: str) -> tuple[str, str, str]:
    return (_BP + archetype, f"{archetype}:{component}", _BPC + component_type)


# ---- protobuf (wire format: varints and length-delimited fields) ---------------------------------


def varint(n: int) -> bytes:
    out = bytearray()
    while True:
        low = n & 0x7F
        n >>= 7
        if n:
            out.append(low | 0x80)
        else:
            out.append(low)
            return bytes(out)


def pb_int(field: int, n: int) -> bytes:
    return varint(field << 3) + varint(n)


def pb_bytes(field: int, payload: bytes) -> bytes:
    return varint(field << 3 | 2) + varint(len(payload)) + payload


def pb_tuid(field: int, tuid: tuple[int, int]) -> bytes:
    return pb_bytes(field, b"\x09" + struct.pack("<Q", tuid[0]) + b"\x11" + struct.pack("<Q", tuid[1]))


def make_store_id(kind: int, recording_id: str, application_id: str = APPLICATION_ID) -> bytes:
    return (
        pb_int(1, kind)
        + pb_bytes(2, recording_id.encode("utf-8", "surrogateescape"))
        + pb_bytes(3, pb_bytes(1, application_id.encode()))
    )


def encode_store_info(store_id: bytes) -> bytes:
    v = sys.version_info
    python = pb_int(1, v.major) + pb_int(2, v.minor) + pb_int(3, v.micro)
    source = pb_int(1, _PYTHON_SDK) + pb_bytes(2, pb_bytes(1, python))
    major, minor, patch = RERUN_VERSION
    bits = major | minor << 8 | patch << 16
    return pb_bytes(2, store_id) + pb_bytes(5, source) + pb_bytes(6, pb_int(1, bits))


# ---- flatbuffers, written front to back -------------------------------------------------------------
# A table is written as its vtable, then the table (its offset to the vtable, the inline fields,
# each aligned to its size), then what its offset fields point to, all after it: flatbuffers'
# offsets point forward. A writer takes the buffer and returns where its object starts.

Writer = Callable[[bytearray], int]
_SIZES = {"B": 1, "h": 2, "i": 4, "q": 8, "o": 4}


def fb_pad(buf: bytearray, n: int) -> None:
    buf.extend(bytes(-len(buf) % n))


def fb_table(*fields: tuple[int, str, Any]) -> Writer:
    """fields: (slot, struct code or "o" for an offset, value or writer)."""

    def write(buf: bytearray) -> int:
        nslots = max((f[0] for f in fields), default=-1) + 1
        fb_pad(buf, 2)
        vt = len(buf)
        buf.extend(bytes(4 + 2 * nslots))
        fb_pad(buf, 4)
        start = len(buf)
        buf.extend(struct.pack("<i", start - vt))
        at: dict[int, int] = {}
        for slot, code, value in sorted(fields, key=lambda f: -_SIZES[f[1]]):
            fb_pad(buf, _SIZES[code])
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


def fb_string(text: str) -> Writer:
    def write(buf: bytearray) -> int:
        fb_pad(buf, 4)
        pos = len(buf)
        data = text.encode("utf-8", "surrogateescape")
        buf.extend(struct.pack("<I", len(data)) + data + b"\0")
        return pos

    return write


def fb_vector(items: list[Writer]) -> Writer:
    def write(buf: bytearray) -> int:
        fb_pad(buf, 4)
        pos = len(buf)
        buf.extend(struct.pack("<I", len(items)) + bytes(4 * len(items)))
        for i, item in enumerate(items):
            slot = pos + 4 + 4 * i
            struct.pack_into("<I", buf, slot, item(buf) - slot)
        return pos

    return write


def fb_structs(pairs: list[tuple[int, int]]) -> Writer:
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


def fb_int32_vector(values: list[int]) -> Writer:
    """A vector of int32 (a Union's typeIds)."""

    def write(buf: bytearray) -> int:
        fb_pad(buf, 4)
        pos = len(buf)
        buf.extend(struct.pack(f"<I{len(values)}i", len(values), *values))
        return pos

    return write


def flatbuffer(root: Writer) -> bytes:
    buf = bytearray(4)
    struct.pack_into("<I", buf, 0, root(buf))
    fb_pad(buf, 8)
    return bytes(buf)


# ---- Arrow IPC (the columnar format's stream: Schema, RecordBatch, end of stream) -----------------

# Type union members (Schema.fbs) and their tables
NULL, INT, FLOAT, UTF8, TIMESTAMP, LIST, STRUCT, UNION, FIXED_BINARY, FIXED_LIST = 1, 2, 3, 5, 10, 12, 13, 14, 15, 16
DENSE = 1  # UnionMode
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
        return fb_table(
            (0, "o", fb_string(self.name)),
            (1, "B", int(self.nullable)),
            (2, "B", self.type_id),
            (3, "o", fb_table(*self.type_fields)),
            (5, "o", fb_vector([c.writer() for c in self.children])),
            (6, "o", key_values(self.meta)),
        )


def key_values(meta: dict[str, str]) -> Writer:
    return fb_vector([fb_table((0, "o", fb_string(k)), (1, "o", fb_string(v))) for k, v in meta.items()])


def int_type(bits: int, signed: bool) -> tuple[tuple[int, str, Any], ...]:
    return ((0, "i", bits), (1, "B", int(signed)))


class Column:
    """A column of a chunk: its field, its array's nodes and buffers (depth first, as IPC wants)."""

    def __init__(self, field: Field, nodes: list[tuple[int, int]], buffers: list[bytes]) -> None:
        self.field, self.nodes, self.buffers = field, nodes, buffers


def le_bytes(a: array) -> bytes:
    if sys.byteorder == "big":
        a = array(a.typecode, a)
        a.byteswap()
    return a.tobytes()


def one_per_row(n: int, per_row: int = 1) -> bytes:
    """A list column's offsets when every row holds `per_row` values."""
    return le_bytes(array("i", range(0, n * per_row + 1, per_row)))


def ipc_message(header_type: int, header: Writer, body_len: int) -> bytes:
    meta = flatbuffer(
        fb_table((0, "h", _V5), (1, "B", header_type), (2, "o", header), (3, "q", body_len)),
    )
    return struct.pack("<Ii", 0xFFFFFFFF, len(meta)) + meta


def arrow_stream(columns: list[Column], rows: int, meta: dict[str, str]) -> list[bytes]:
    """The Arrow IPC stream of one record batch, as parts to write one after the other."""
    schema = fb_table(
        (0, "h", 0),  # little-endian
        (1, "o", fb_vector([c.field.writer() for c in columns])),
        (2, "o", key_values(meta)),
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
    batch = fb_table((0, "q", rows), (1, "o", fb_structs(nodes)), (2, "o", fb_structs(spans)))
    return [
        ipc_message(_MESSAGE_SCHEMA, schema, 0),
        ipc_message(_MESSAGE_BATCH, batch, size),
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


def row_id_column(ids: bytes, n: int) -> Column:
    field = Field(
        ROW_ID,
        FIXED_BINARY,
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


def index_column(name: str, timestamp: bool, values: bytes, ordered: bool) -> Column:
    """An index (time line) column: int64 sequence or timestamp in ns (`values`: little-endian
    int64s; `ordered`: whether they never decrease, which rerun is told)."""
    meta = {"rerun:index_name": name}
    if ordered:
        meta["rerun:is_sorted"] = "true"
    meta["rerun:kind"] = "index"
    kind = (TIMESTAMP, ((0, "h", 3),)) if timestamp else (INT, int_type(64, True))
    return Column(Field(name, kind[0], kind[1], meta=meta), [(len(values) // 8, 0)], [b"", values])


def component_meta(desc: tuple[str, str, str]) -> dict[str, str]:
    archetype, component, component_type = desc
    return {
        "rerun:archetype": archetype,
        "rerun:component": component,
        "rerun:component_type": component_type,
        "rerun:kind": "data",
    }


def list_field(desc: tuple[str, str, str], item: Field) -> Field:
    return Field(desc[1], LIST, children=(item,), meta=component_meta(desc))


def scalars_column(values: bytes, n: int, series: int = 1) -> Column:
    """Scalars:scalars, a list of `series` float64s a row (`values`: n x series little-endian
    float64s, row by row)."""
    item = Field("item", FLOAT, ((0, "h", 2),))
    return Column(list_field(SCALARS, item), [(n, 0), (n * series, 0)], [b"", one_per_row(n, series), b"", values])


def int64_list_column(desc: tuple[str, str, str], values: list[int]) -> Column:
    n = len(values)
    item = Field("item", INT, int_type(64, True))
    return Column(list_field(desc, item), [(n, 0), (n, 0)], [b"", one_per_row(n), b"", le_bytes(array("q", values))])


def view_columns(kind: str, name: str, origin: str) -> list[Any]:
    """A blueprint view's own row: its class, its name and its origin (the .rrd's and the live
    recording's, logs/rerun_sender.py)."""
    return [
        text_list_column(bp("ViewBlueprint", "class_identifier", "ViewClass"), [[kind]]),
        text_list_column(
            ("rerun.blueprint.archetypes.ViewBlueprint", "ViewBlueprint:display_name", "rerun.components.Name"),
            [[name]],
        ),
        text_list_column(bp("ViewBlueprint", "space_origin", "ViewOrigin"), [[origin]]),
    ]


def text_list_column(desc: tuple[str, str, str], rows: list[list[str]]) -> Column:
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
    item = Field("item", UTF8)
    return Column(list_field(desc, item), [(n, 0), (m, 0)], [b"", le_bytes(outer), b"", le_bytes(inner), bytes(data)])


def uint8_list_column(desc: tuple[str, str, str], values: list[int]) -> Column:
    n = len(values)
    item = Field("item", INT, int_type(8, False))
    return Column(list_field(desc, item), [(n, 0), (n, 0)], [b"", one_per_row(n), b"", bytes(values)])


def uuid_list_column(desc: tuple[str, str, str], ids: list[bytes]) -> Column:
    """A list of one 16-byte id a row (FixedSizeList of 16 uint8)."""
    n = len(ids)
    byte = Field("item", INT, int_type(8, False), nullable=False)
    item = Field("item", FIXED_LIST, ((0, "i", 16),), children=(byte,))
    col = list_field(desc, item)
    return Column(col, [(n, 0), (n, 0), (16 * n, 0)], [b"", one_per_row(n), b"", b"", b"".join(ids)])


class Messages:
    """rerun's messages of one stream, each handed to the subclass's `_frame` as it is made (a .rrd
    file's frame: logs/rrdfile.py; a gRPC-web request to a proxy: logs/rerun_sender.py)."""

    tuids: Tuids

    def _frame(self, kind: int, parts: list[bytes]) -> None:
        raise NotImplementedError

    def store_info(self, store_id: bytes) -> None:
        self._frame(SET_STORE_INFO, [pb_tuid(1, self.tuids.next()) + pb_bytes(2, encode_store_info(store_id))])

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
            pb_bytes(1, store_id)
            + pb_tuid(6, chunk_id)
            + pb_int(2, _COMPRESSION_NONE)
            + pb_int(3, size)
            + pb_int(4, _ARROW_IPC)
            + pb_int(7, int(static))
            + varint(5 << 3 | 2)
            + varint(size)
        )
        self._frame(ARROW_MSG, [head, *payload])

    def activate(self, blueprint_id: bytes, make_active: bool = False) -> None:
        """The blueprint made the default (a .rrd's), and also the active one (the live view's, as
        the SDK's send_blueprint(.., make_active=True, make_default=True))."""
        self._frame(ACTIVATE, [pb_bytes(1, blueprint_id) + (pb_int(2, 1) if make_active else b"") + pb_int(3, 1)])
