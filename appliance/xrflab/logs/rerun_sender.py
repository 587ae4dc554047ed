"""The live recording's sender (logs/rerun_live.py): rerun 0.41's messages made here and written to
the run's proxy (rerun_servers.LiveProxy) by gRPC-web over HTTP/1.1, without the rerun SDK.

The SDK (``rr.RecordingStream`` + ``connect_grpc``) was imported in the appliance only for this,
and with it pyarrow and rerun_bindings: ~55 MB RSS that never left once a viewer had watched a
run (issue 30 item 4, the appliance's ≤ 250 MB). The messages are the ones a ``.rrd`` carries
(logs/rerun_wire.py encodes them: Arrow IPC, protobuf and chunk metadata, as for the `.rrd`
download), the column bodies NumPy's bytes:

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
rerun_wire.py; tests/logs/test_live_sender.py fails when the pinned SDK no longer reads what a
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
from .rerun_wire import (
    APPLICATION_ID,
    BLUEPRINT,
    DENSE,
    GRID,
    INT,
    LEVEL,
    LIST,
    NULL,
    RECORDING,
    START_TIME,
    STRUCT,
    TEXT,
    UNION,
    UTF8,
    Column,
    Field,
    Messages,
    Tuids,
    bp,
    component_meta,
    escape_part,
    fb_int32_vector,
    index_column,
    int64_list_column,
    int_type,
    make_store_id,
    pb_bytes,
    row_id_column,
    scalars_column,
    text_list_column,
    uint8_list_column,
    uuid_list_column,
    view_columns,
)

log = logging.getLogger("xrflab.logs.live")

WRITE_MESSAGES = "/rerun.sdk_comms.v1alpha1.MessageProxyService/WriteMessages"
GRPC_WEB = {"content-type": "application/grpc-web+proto", "x-grpc-web": "1"}
# A POST's connect and each read/write: the proxy answers a batch in milliseconds, unless a slow
# viewer holds its broadcast (rerun then blocks its writers); past this the batch is given up.
CONNECT_S = 2.0
TIMEOUT_S = 5.0

_COLLAPSED = 2  # rerun.blueprint.components.PanelState
_SERIES_NAMES = ("rerun.archetypes.SeriesLines", "SeriesLines:names", "rerun.components.Name")
_TIME_RANGES = bp("VisibleTimeRanges", "ranges", "VisibleTimeRange")
_CURSOR_RELATIVE = 1  # the TimeRangeBoundary union's member (0 is its null marker)


class _Frames(Messages):
    """rerun's messages, each made a gRPC-web data frame of WriteMessages (a
    WriteMessagesRequest{log_msg = 1}, the LogMsg's field = the .rrd frame's kind) and kept."""

    def __init__(self) -> None:
        self.tuids = Tuids()
        self.out: list[bytes] = []

    def _frame(self, kind: int, parts: list[bytes]) -> None:
        request = pb_bytes(1, pb_bytes(kind, b"".join(parts)))
        self.out.append(b"\x00" + struct.pack(">I", len(request)) + request)

    def take(self) -> list[bytes]:
        out, self.out = self.out, []
        return out


def _index(name: str, timestamp: bool, values: np.ndarray) -> Column:
    """A timeline's column: int64 sequence, or timestamp in ns since the epoch."""
    v = np.ascontiguousarray(values, dtype="<i8")
    return index_column(name, timestamp, v.tobytes(), len(v) < 2 or bool(np.all(v[1:] >= v[:-1])))


def _boundary(name: str) -> Field:
    """A TimeRangeBoundary: the dense union rerun's blueprint stores (members as the SDK's)."""
    members = (
        Field("_null_markers", NULL),
        Field("CursorRelative", INT, int_type(64, True), nullable=False),
        Field("Absolute", INT, int_type(64, True), nullable=False),
        Field("Infinite", NULL),
    )
    return Field(name, UNION, ((0, "h", DENSE), (1, "o", fb_int32_vector([0, 1, 2, 3]))), children=members)


def _cursor_ranges(ranges: list[tuple[str, int]]) -> Column:
    """VisibleTimeRanges:ranges of one row: for each (timeline, span), from `span` before the
    time cursor to the cursor (TimeRangeBoundary.cursor_relative)."""
    m = len(ranges)
    timeline = Field("timeline", UTF8, nullable=False)
    rng = Field("range", STRUCT, children=(_boundary("start"), _boundary("end")), nullable=False)
    item = Field("item", STRUCT, children=(timeline, rng))
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
    return Column(Field(_TIME_RANGES[1], LIST, children=(item,), meta=component_meta(_TIME_RANGES)), nodes, buffers)


def _path(entity: str) -> str:
    """An entity path as the SDK writes it in a chunk: from the root."""
    return entity if entity.startswith("/") else "/" + entity


class LiveSender:
    """One run's recording on its proxy: the calls LiveRerun makes, each encoding its chunk; ``flush``
    sends them. One thread (the recording's) uses it."""

    def __init__(self, url: Callable[[], str], recording_id: str) -> None:
        """`url`: where the proxy listens now (http://127.0.0.1:<port>), asked at each POST."""
        self._url = url
        self._store = make_store_id(RECORDING, recording_id)
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
        rows = row_id_column(self._enc.tuids.rows(1), 1)
        self._enc.chunk(self._store, "/__properties", [rows, int64_list_column(START_TIME, [time.time_ns()])], 1, True)
        self._head = self._enc.take()
        self._pending += self._head

    def blueprint(self, groups: list[str], telemetry: list[str], span_s: float, freq: int) -> None:
        """The live blueprint (rerun_live.live_blueprint's layout): a TimeSeriesView per variable group
        (`groups`, sorted: ``log: <group>`` at /log/<group>) and per telemetry group (at
        /telemetry/<name>) in one grid, each the last `span_s` on both timelines (cycle at `freq`),
        the blueprint and selection panels collapsed, the time panel on ``cycle``."""
        enc = self._enc
        store = make_store_id(BLUEPRINT, f"rec_{uuid.uuid4().hex}")
        enc.store_info(store)
        views = [(f"log: {g}", "/log/" + escape_part(g)) for g in groups]
        views += [(t, f"/telemetry/{t}") for t in telemetry]
        ids = [uuid.uuid4() for _ in views]
        container = uuid.uuid4()
        now = np.array([time.time_ns()], dtype=np.int64)
        ranges = _cursor_ranges([("cycle", int(span_s * freq)), ("time", int(span_s * 1e9))])

        def one_row(entity: str, *columns: Column) -> None:
            indexes = [_index("blueprint", False, np.zeros(1, dtype=np.int64)), _index("log_time", True, now)]
            enc.chunk(store, entity, [row_id_column(enc.tuids.rows(1), 1), *indexes, *columns], 1)

        for (name, origin), vid in zip(views, ids):
            one_row(f"/view/{vid}", *view_columns("TimeSeries", name, origin))
            one_row(
                f"/view/{vid}/ViewContents",
                text_list_column(bp("ViewContents", "query", "QueryExpression"), [["$origin/**"]]),
            )
            one_row(f"/view/{vid}/VisibleTimeRanges", ranges)
        one_row(
            f"/container/{container}",
            uint8_list_column(bp("ContainerBlueprint", "container_kind", "ContainerKind"), [GRID]),
            text_list_column(bp("ContainerBlueprint", "contents", "IncludedContent"), [[f"view/{v}" for v in ids]]),
        )
        one_row(
            "/viewport",
            uuid_list_column(bp("ViewportBlueprint", "root_container", "RootContainer"), [container.bytes]),
        )
        for panel in ("/blueprint_panel", "/selection_panel"):
            one_row(panel, uint8_list_column(bp("PanelBlueprint", "state", "PanelState"), [_COLLAPSED]))
        one_row("/time_panel", text_list_column(bp("TimePanelBlueprint", "timeline", "TimelineName"), [["cycle"]]))
        # make_active and make_default (the SDK's send_blueprint(.., True, True))
        enc.activate(store, make_active=True)
        self._blueprint = enc.take()
        self._pending += self._blueprint

    def series_names(self, entity: str, names: list[str]) -> None:
        """The names of a multi-series entity's series (static: the SDK's log(.., static=True))."""
        entity = _path(entity)
        rows = row_id_column(self._enc.tuids.rows(1), 1)
        self._enc.chunk(self._store, entity, [rows, text_list_column(_SERIES_NAMES, [names])], 1, static=True)
        (frame,) = self._enc.take()
        self._names[entity] = frame
        self._pending.append(frame)

    def scalars(self, entity: str, cycle: np.ndarray, time_ns: np.ndarray, values: np.ndarray) -> None:
        """Rows of `values` (rows x series, float64) at `cycle` and `time_ns` (ns since the epoch)."""
        n = len(values)
        if n == 0:
            return
        rows = values.reshape(n, -1)
        columns = [
            row_id_column(self._enc.tuids.rows(n), n),
            _index("cycle", False, cycle),
            _index("time", True, time_ns),
            scalars_column(np.ascontiguousarray(rows, dtype="<f8").tobytes(), n, rows.shape[1]),
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
            row_id_column(self._enc.tuids.rows(n), n),
            _index("cycle", False, cycle),
            _index("time", True, time_ns),
            text_list_column(LEVEL, [[level]] * n),
            text_list_column(TEXT, [[t] for t in texts]),
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
