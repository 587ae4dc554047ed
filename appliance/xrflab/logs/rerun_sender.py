"""The live recording's sender (logs/rerun_live.py): rerun 0.41's messages made here and written to
the run's proxy (rerun_servers.LiveProxy) by gRPC-web over HTTP/1.1, without the rerun SDK.

The SDK (``rr.RecordingStream`` + ``connect_grpc``) was imported in the appliance only for this,
and with it pyarrow and rerun_bindings: ~55 MB RSS that never left once a viewer had watched a
run (issue 30 item 4, the appliance's ≤ 250 MB). The messages are the ones a ``.rrd`` carries
(logs/rrdfile.py writes their Arrow IPC, protobuf and chunk metadata; its primitives are used
here), the column bodies NumPy's bytes:

- the recording's store info and its ``/__properties`` start time, as the SDK sends them when a
  recording is made;
- the live blueprint (``blueprint``): one time-series view per variable group and per telemetry
  group, each showing the last ``LIVE_SPAN_S`` before the time cursor, panels collapsed, the time
  panel on ``cycle``; made active and default, as ``rr.bindings.send_blueprint(.., True, True)``;
- the series' names of a multi-series entity (``SeriesLines:names``, static), ``Scalars`` columns
  (a list of the series' values a row) and the ``TextLog`` of parameter changes, on the ``cycle``
  (sequence) and ``time`` (ns since the epoch) timelines, as ``send_columns`` made them.

Each call encodes its chunk at once; ``flush`` sends what the calls made since the last one in one
POST of ``WriteMessages`` (a client stream of gRPC-web data frames, each a WriteMessagesRequest
holding one LogMsg), on a keep-alive connection. Chunks go uncompressed (the SDK LZ4-compresses;
float64 samples barely compress, and LZ4 in Python would cost more than it saves).

A POST that fails (the proxy stopped, restarted on another port, or held the stream past
``TIMEOUT_S`` for a slow viewer) loses that batch, as the SDK's client dropped what it could not
deliver: the live view is for watching, every record is in the run's log. The next POST starts
with the store info, blueprint and series names again, which a restarted proxy no longer holds,
and goes to wherever the proxy listens now (``url`` is asked at each POST).

The protobuf field numbers (rerun's ``sdk_comms.proto``/``log_msg.proto``, 0.41) are here and in
rrdfile.py; tests/logs/test_live_sender.py fails when the pinned SDK no longer reads what a
ReadMessages reader gets as what its own sender sent.
"""

from __future__ import annotations

import logging
import struct
import time
import uuid
from collections.abc import Callable
from typing import Any

import numpy as np

from .. import loopback
from .rrdfile import (
    _ACTIVATE,
    _BLUEPRINT,
    _FLOAT,
    _INT,
    _LEVEL,
    _LIST,
    _RECORDING,
    _SCALARS,
    _START,
    _TEXT,
    _TIMESTAMP,
    _UTF8,
    APPLICATION_ID,
    GRID,
    Column,
    Field,
    RrdWriter,
    Tuids,
    Writer,
    _bp,
    _component_meta,
    _int,
    _int64_list_column,
    _list_field,
    _pb_bytes,
    _pb_int,
    _row_id_column,
    _store_id,
    _text_list_column,
    _uint8_list_column,
    _uuid_list_column,
    _view_columns,
)
from .rrdfile import escape_part as _escape_ascii

log = logging.getLogger("xrflab.logs.live")

WRITE_MESSAGES = "/rerun.sdk_comms.v1alpha1.MessageProxyService/WriteMessages"
GRPC_WEB = {"content-type": "application/grpc-web+proto", "x-grpc-web": "1"}
# A POST's connect and each read/write: the proxy answers a batch in milliseconds, unless a slow
# viewer holds its broadcast (rerun then blocks its writers); past this the batch is given up.
CONNECT_S = 2.0
TIMEOUT_S = 5.0

_STRUCT, _UNION, _NULL = 13, 14, 1  # Arrow Type union members (Schema.fbs)
_DENSE = 1  # UnionMode
_COLLAPSED = 2  # rerun.blueprint.components.PanelState
_SERIES_NAMES = ("rerun.archetypes.SeriesLines", "SeriesLines:names", "rerun.components.Name")
_TIME_RANGES = _bp("VisibleTimeRanges", "ranges", "VisibleTimeRange")
_CURSOR_RELATIVE = 1  # the TimeRangeBoundary union's member (0 is its null marker)


class _Frames(RrdWriter):
    """rrdfile's writer of messages, each made a gRPC-web data frame of WriteMessages (a
    WriteMessagesRequest{log_msg = 1}, the LogMsg's field = the .rrd frame's kind) and kept."""

    def __init__(self) -> None:  # (no stream header: the frames go to a proxy, not a file)
        self.tuids = Tuids()
        self.out: list[bytes] = []

    def _frame(self, kind: int, parts: list[bytes]) -> None:
        request = _pb_bytes(1, _pb_bytes(kind, b"".join(parts)))
        self.out.append(b"\x00" + struct.pack(">I", len(request)) + request)

    def take(self) -> list[bytes]:
        out, self.out = self.out, []
        return out


def _index(name: str, timestamp: bool, values: np.ndarray) -> Column:
    """A timeline's column: int64 sequence, or timestamp in ns since the epoch."""
    v = np.ascontiguousarray(values, dtype="<i8")
    meta = {"rerun:index_name": name}
    if len(v) < 2 or bool(np.all(v[1:] >= v[:-1])):
        meta["rerun:is_sorted"] = "true"
    meta["rerun:kind"] = "index"
    kind = (_TIMESTAMP, ((0, "h", 3),)) if timestamp else (_INT, _int(64, True))
    return Column(Field(name, kind[0], kind[1], meta=meta), [(len(v), 0)], [b"", v.tobytes()])


def _scalars(values: np.ndarray) -> Column:
    """Scalars:scalars: a list of the row's series values (rows x series, float64) a row."""
    n, k = values.shape
    item = Field("item", _FLOAT, ((0, "h", 2),))
    offsets = (np.arange(n + 1, dtype="<i4") * k).tobytes()
    body = np.ascontiguousarray(values, dtype="<f8").tobytes()
    return Column(_list_field(_SCALARS, item), [(n, 0), (n * k, 0)], [b"", offsets, b"", body])


def _boundary(name: str) -> Field:
    """A TimeRangeBoundary: the dense union rerun's blueprint stores (members as the SDK's)."""
    members = (
        Field("_null_markers", _NULL),
        Field("CursorRelative", _INT, _int(64, True), nullable=False),
        Field("Absolute", _INT, _int(64, True), nullable=False),
        Field("Infinite", _NULL),
    )
    return Field(name, _UNION, ((0, "h", _DENSE), (1, "o", _int32_vector([0, 1, 2, 3]))), children=members)


def _int32_vector(values: list[int]) -> Writer:
    """A flatbuffers vector of int32 (a Union's typeIds)."""

    def write(buf: bytearray) -> int:
        while len(buf) % 4:
            buf.append(0)
        pos = len(buf)
        buf.extend(struct.pack(f"<I{len(values)}i", len(values), *values))
        return pos

    return write


def _cursor_ranges(ranges: list[tuple[str, int]]) -> Column:
    """VisibleTimeRanges:ranges of one row: for each (timeline, span), from `span` before the
    time cursor to the cursor (TimeRangeBoundary.cursor_relative)."""
    m = len(ranges)
    timeline = Field("timeline", _UTF8, nullable=False)
    rng = Field("range", _STRUCT, children=(_boundary("start"), _boundary("end")), nullable=False)
    item = Field("item", _STRUCT, children=(timeline, rng))
    names = [t.encode() for t, _ in ranges]
    name_offsets = np.cumsum([0] + [len(n) for n in names], dtype="<i4").tobytes()
    types = bytes([_CURSOR_RELATIVE]) * m
    at = np.arange(m, dtype="<i4").tobytes()

    def union(values: list[int]) -> tuple[list[tuple[int, int]], list[bytes]]:
        # the union (type ids, offsets), then each member: _null_markers and Infinite are Null
        # arrays (no buffers), CursorRelative holds the values, Absolute none
        nodes = [(m, 0), (0, 0), (m, 0), (0, 0), (0, 0)]
        return nodes, [types, at, b"", np.array(values, dtype="<i8").tobytes(), b"", b""]

    start_nodes, start_bufs = union([-span for _, span in ranges])
    end_nodes, end_bufs = union([0] * m)
    nodes = [(1, 0), (m, 0), (m, 0), (m, 0), *start_nodes, *end_nodes]
    buffers = [
        b"",  # list: validity
        np.array([0, m], dtype="<i4").tobytes(),  # offsets
        b"",  # item struct: validity
        b"",  # timeline: validity, offsets, data
        name_offsets,
        b"".join(names),
        b"",  # range struct: validity
        *start_bufs,
        *end_bufs,
    ]
    return Column(Field(_TIME_RANGES[1], _LIST, children=(item,), meta=_component_meta(_TIME_RANGES)), nodes, buffers)


def escape_part(part: str) -> str:
    """An entity path part as rr.escape_entity_path_part writes it: rrdfile's escaping of ASCII, and
    a letter or digit beyond ASCII as it is (rerun's `char::is_alphanumeric`; where Python's
    Unicode tables say otherwise, as \\u{XXXX}, which rerun reads as the same character: the path
    is the same, only its text differs)."""
    return "".join(ch if not ch.isascii() and ch.isalnum() else _escape_ascii(ch) for ch in part)


def _path(entity: str) -> str:
    """An entity path as the SDK writes it in a chunk: from the root."""
    return entity if entity.startswith("/") else "/" + entity


class LiveSender:
    """One run's recording on its proxy: the calls LiveRerun makes, each encoding its chunk; ``flush``
    sends them. One thread (the recording's) uses it."""

    def __init__(self, url: Callable[[], str], recording_id: str) -> None:
        """`url`: where the proxy listens now (http://127.0.0.1:<port>), asked at each POST."""
        self._url = url
        self._store = _store_id(_RECORDING, recording_id)
        self._enc = _Frames()
        self._client: Any = None  # httpx.Client, from connect on
        self._pending: list[bytes] = []
        # What a proxy must hold before the data, sent again after a failed POST: the store info
        # and start time, the blueprint, each entity's series names
        self._head: list[bytes] = []
        self._blueprint: list[bytes] = []
        self._names: dict[str, bytes] = {}
        self._resend = False
        self.failed_posts = 0  # batches given up (the proxy gone or too slow)
        self.posts = 0

    def connect(self) -> None:
        """The recording's store info and start time (sent with the first batch)."""
        import httpx  # (the appliance's read proxy has it loaded already: server/http/rerun.py)

        self._client = loopback.client(headers=GRPC_WEB, timeout=httpx.Timeout(TIMEOUT_S, connect=CONNECT_S))
        self._enc.store_info(self._store)
        rows = _row_id_column(self._enc.tuids.rows(1), 1)
        self._enc.chunk(self._store, "/__properties", [rows, _int64_list_column(_START, [time.time_ns()])], 1, True)
        self._head = self._enc.take()
        self._pending += self._head

    def blueprint(self, groups: list[str], telemetry: list[str], span_s: float, freq: int) -> None:
        """The live blueprint (rerun_live.live_blueprint's layout): a TimeSeriesView per variable group
        (`groups`, sorted: ``log: <group>`` at /log/<group>) and per telemetry group (at
        /telemetry/<name>) in one grid, each the last `span_s` on both timelines (cycle at `freq`),
        the blueprint and selection panels collapsed, the time panel on ``cycle``."""
        enc = self._enc
        store = _store_id(_BLUEPRINT, f"rec_{uuid.uuid4().hex}")
        enc.store_info(store)
        views = [(f"log: {g}", "/log/" + escape_part(g)) for g in groups]
        views += [(t, f"/telemetry/{t}") for t in telemetry]
        ids = [uuid.uuid4() for _ in views]
        container = uuid.uuid4()
        now = np.array([time.time_ns()], dtype=np.int64)
        ranges = _cursor_ranges([("cycle", int(span_s * freq)), ("time", int(span_s * 1e9))])

        def one_row(entity: str, *columns: Column) -> None:
            indexes = [_index("blueprint", False, np.zeros(1, dtype=np.int64)), _index("log_time", True, now)]
            enc.chunk(store, entity, [_row_id_column(enc.tuids.rows(1), 1), *indexes, *columns], 1)

        for (name, origin), vid in zip(views, ids):
            one_row(f"/view/{vid}", *_view_columns("TimeSeries", name, origin))
            one_row(
                f"/view/{vid}/ViewContents",
                _text_list_column(_bp("ViewContents", "query", "QueryExpression"), [["$origin/**"]]),
            )
            one_row(f"/view/{vid}/VisibleTimeRanges", ranges)
        one_row(
            f"/container/{container}",
            _uint8_list_column(_bp("ContainerBlueprint", "container_kind", "ContainerKind"), [GRID]),
            _text_list_column(_bp("ContainerBlueprint", "contents", "IncludedContent"), [[f"view/{v}" for v in ids]]),
        )
        one_row(
            "/viewport",
            _uuid_list_column(_bp("ViewportBlueprint", "root_container", "RootContainer"), [container.bytes]),
        )
        for panel in ("/blueprint_panel", "/selection_panel"):
            one_row(panel, _uint8_list_column(_bp("PanelBlueprint", "state", "PanelState"), [_COLLAPSED]))
        one_row("/time_panel", _text_list_column(_bp("TimePanelBlueprint", "timeline", "TimelineName"), [["cycle"]]))
        # make_active and make_default (the SDK's send_blueprint(.., True, True))
        enc._frame(_ACTIVATE, [_pb_bytes(1, store) + _pb_int(2, 1) + _pb_int(3, 1)])
        self._blueprint = enc.take()
        self._pending += self._blueprint

    def series_names(self, entity: str, names: list[str]) -> None:
        """The names of a multi-series entity's series (static: the SDK's log(.., static=True))."""
        entity = _path(entity)
        rows = _row_id_column(self._enc.tuids.rows(1), 1)
        self._enc.chunk(self._store, entity, [rows, _text_list_column(_SERIES_NAMES, [names])], 1, static=True)
        (frame,) = self._enc.take()
        self._names[entity] = frame
        self._pending.append(frame)

    def scalars(self, entity: str, cycle: np.ndarray, time_ns: np.ndarray, values: np.ndarray) -> None:
        """Rows of `values` (rows x series, float64) at `cycle` and `time_ns` (ns since the epoch)."""
        n = len(values)
        if n == 0:
            return
        columns = [
            _row_id_column(self._enc.tuids.rows(n), n),
            _index("cycle", False, cycle),
            _index("time", True, time_ns),
            _scalars(values.reshape(n, -1)),
        ]
        self._enc.chunk(self._store, _path(entity), columns, n)
        self._pending += self._enc.take()

    def texts(self, entity: str, cycle: np.ndarray, t_s: np.ndarray, texts: list[str], level: str) -> None:
        """Text log entries (TextLog: text and level) at `cycle` and `t_s` (seconds since the epoch,
        float64: made ns as the SDK's TimeColumn(timestamp=...) makes them, truncated)."""
        n = len(texts)
        if n == 0:
            return
        time_ns = (np.asarray(t_s, dtype=np.float64) * 1e9).astype("datetime64[ns]").view(np.int64)
        columns = [
            _row_id_column(self._enc.tuids.rows(n), n),
            _index("cycle", False, cycle),
            _index("time", True, time_ns),
            _text_list_column(_LEVEL, [[level]] * n),
            _text_list_column(_TEXT, [[t] for t in texts]),
        ]
        self._enc.chunk(self._store, _path(entity), columns, n)
        self._pending += self._enc.take()

    def flush(self) -> bool:
        """POST what was made since the last flush (one WriteMessages call); False when it did not
        reach the proxy (the batch is lost, and the next starts with what a proxy needs first)."""
        if not self._pending or self._client is None:
            return True
        frames, self._pending = self._pending, []
        if self._resend:
            frames = [*self._head, *self._blueprint, *self._names.values(), *frames]
        import httpx

        status = ""
        try:
            r = self._client.post(self._url() + WRITE_MESSAGES, content=b"".join(frames))
            status = _grpc_status(r.status_code, r.headers, r.content)
        except httpx.HTTPError as e:
            status = f"{type(e).__name__}: {e}"
        self.posts += 1
        if status == "0":
            if self._resend:
                log.info("live rerun: the proxy takes the recording again")
            self._resend = False
            return True
        if not self._resend:  # once per outage, not at every batch
            log.warning("live rerun: a batch did not reach the proxy (%s); dropped", status)
        self._resend = True
        self.failed_posts += 1
        return False

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None


def _grpc_status(http_status: int, headers: Any, body: bytes) -> str:
    """The call's gRPC status ("0": OK): a trailers-only answer has it in the headers, a gRPC-web
    answer with a body in its trailer frame (flag 0x80) at the end."""
    if http_status != 200:
        return f"HTTP {http_status}"
    if "grpc-status" in headers:
        return str(headers["grpc-status"])
    pos = 0
    while len(body) - pos >= 5:
        flag, length = body[pos], struct.unpack(">I", body[pos + 1 : pos + 5])[0]
        if flag & 0x80:
            for line in body[pos + 5 : pos + 5 + length].decode("latin-1").split("\r\n"):
                key, _, value = line.partition(":")
                if key.strip().lower() == "grpc-status":
                    return value.strip()
        pos += 5 + length
    return "no grpc-status"


__all__ = ["APPLICATION_ID", "LiveSender", "escape_part"]
