"""Enough of rerun's live stream to know how old it is: each gRPC-web data frame of ReadMessages
(grpcweb.py) is a ``ReadMessagesResponse{LogMsg log_msg = 1}``; a ``LogMsg`` holds one of
SetStoreInfo (1), ArrowMsg (2) or BlueprintActivationCommand (3); an ``ArrowMsg`` names its
store (``StoreId{kind = 1, recording_id = 2}``, kind 1 = a recording, 2 = a blueprint), its
compression (2 = LZ4 block, the whole payload; 1 or 0 = none), the uncompressed size and an Arrow
IPC stream (schema + one record batch: one chunk of one entity). Field numbers from rerun's
``log_msg.proto``/``sdk_comms.proto`` (rerun 0.41); the protobuf wire format is read by hand
(varints and length-delimited fields are all these messages use), the Arrow payload by pyarrow.

The appliance's live recording (logs/rerun_live.py, ``LiveRerun._indexes``) carries a ``time`` index of
wall-clock nanoseconds (the loop's sample time + the run's wall offset): the newest value in a
message is the newest sample it brings, so arrival time - that = how far the viewer is behind."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

STORE_RECORDING = 1
COMPRESSION_LZ4 = 2
TIME_COLUMN = "time"


def _varint(buf: bytes, pos: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        b = buf[pos]
        pos += 1
        value |= (b & 0x7F) << shift
        if not b & 0x80:
            return value, pos
        shift += 7


def fields(buf: bytes) -> Iterator[tuple[int, int | bytes]]:
    """(field number, value) of a protobuf message: ints for varints, bytes for the rest."""
    pos = 0
    while pos < len(buf):
        key, pos = _varint(buf, pos)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, pos = _varint(buf, pos)
            yield number, value
        elif wire == 2:
            length, pos = _varint(buf, pos)
            yield number, buf[pos : pos + length]
            pos += length
        elif wire in (1, 5):
            size = 8 if wire == 1 else 4
            yield number, buf[pos : pos + size]
            pos += size
        else:
            raise ValueError(f"protobuf wire type {wire} (groups are not used by rerun)")


def _field(buf: bytes, number: int, default: int | bytes | None = None) -> int | bytes | None:
    for n, value in fields(buf):
        if n == number:
            return value
    return default


@dataclass
class Chunk:
    store_kind: int  # STORE_RECORDING or the blueprint's
    recording_id: str
    entity: str  # rerun:entity_path of the chunk
    columns: list[str]
    newest_time_ns: int | None  # max of the `time` index in it, None without one
    oldest_time_ns: int | None = None  # min of it, likewise


def chunk_of(frame: bytes) -> Chunk | None:
    """The chunk a ReadMessages data frame carries, or None (store info, blueprint activation)."""
    import pyarrow as pa
    import pyarrow.ipc as ipc

    log_msg = _field(frame, 1)
    if not isinstance(log_msg, bytes):
        return None
    arrow = _field(log_msg, 2)
    if not isinstance(arrow, bytes):
        return None
    msg = dict(fields(arrow))
    store = msg.get(1, b"")
    store_fields = dict(fields(store)) if isinstance(store, bytes) else {}
    payload = msg.get(5, b"")
    assert isinstance(payload, bytes)
    if msg.get(2) == COMPRESSION_LZ4:
        payload = pa.decompress(payload, decompressed_size=int(msg.get(3, 0)), codec="lz4_raw")  # type: ignore[arg-type]
    table = ipc.open_stream(pa.py_buffer(payload)).read_all()
    newest = oldest = None
    if TIME_COLUMN in table.column_names and table.num_rows:
        values = table.column(TIME_COLUMN).cast(pa.int64())
        newest = int(pa.compute.max(values).as_py())
        oldest = int(pa.compute.min(values).as_py())
    meta = table.schema.metadata or {}
    recording_id = store_fields.get(2, b"")
    return Chunk(
        int(store_fields.get(1, 0)),
        recording_id.decode() if isinstance(recording_id, bytes) else "",
        meta.get(b"rerun:entity_path", b"").decode(),
        table.column_names,
        newest,
        oldest,
    )


# ---- the web viewer's own state (what a person sees) --------------------------------------------
# rerun's web viewer answers ``WebHandle.viewer_state()`` (``window._handle`` on its index.html) with
# an encoded ``GetViewerStateResponse`` (rerun's viewer_control.proto, as of 0.41): recordings = 3,
# each ``ViewerRecording{store_id = 1, timelines = 2}``, a timeline ``ViewerTimeline{timeline = 1
# (Timeline{name = 1}), time_range = 3 (TimeRange{start = 1, end = 2})}``. The end of the `time`
# timeline's range is the newest sample the viewer holds: in its live (following) mode the plots
# end there, so now - that = how far behind live the person looking at it is.


def viewer_time_range(state: bytes, recording_id: str) -> tuple[int | None, int | None]:
    """The oldest and newest `time` values of the recording `recording_id` in a viewer_state()
    answer (its `time` timeline's range), each None while the viewer holds none of it."""
    oldest: int | None = None
    newest: int | None = None
    for n, rec in fields(state):
        if n != 3 or not isinstance(rec, bytes):
            continue
        store = _field(rec, 1, b"")
        if not isinstance(store, bytes) or not store.decode(errors="replace").endswith(recording_id):
            continue
        for m, tl in fields(rec):
            if m != 2 or not isinstance(tl, bytes):
                continue
            timeline = _field(tl, 1, b"")
            name = _field(timeline, 1, b"") if isinstance(timeline, bytes) else b""
            rng = _field(tl, 3)
            if name != TIME_COLUMN.encode() or not isinstance(rng, bytes):
                continue
            start, end = _field(rng, 1), _field(rng, 2)
            if isinstance(start, int):
                oldest = start if oldest is None else min(oldest, start)
            if isinstance(end, int):
                newest = end if newest is None else max(newest, end)
    return oldest, newest


def viewer_newest_ns(state: bytes, recording_id: str) -> int | None:
    """The newest sample the viewer holds (how far behind live it is: now minus that)."""
    return viewer_time_range(state, recording_id)[1]


def viewer_oldest_ns(state: bytes, recording_id: str) -> int | None:
    """The oldest sample the viewer holds (a replay from cycle 0 would make it the run's start)."""
    return viewer_time_range(state, recording_id)[0]


def viewer_recordings(state: bytes) -> dict[str, bool]:
    """Every recording in a viewer_state() answer, by store id (``{kind}:{application}:{recording}``):
    whether it holds a sample yet (a timeline with a range)."""
    out: dict[str, bool] = {}
    for n, rec in fields(state):
        if n != 3 or not isinstance(rec, bytes):
            continue
        store = _field(rec, 1, b"")
        held = any(m == 2 and isinstance(tl, bytes) and _field(tl, 3) is not None for m, tl in fields(rec))
        out[store.decode(errors="replace") if isinstance(store, bytes) else ""] = held
    return out


def viewer_active(state: bytes) -> str | None:
    """The active recording's store id in a viewer_state() answer (``active_store_id = 2``), or None."""
    active = _field(state, 2)
    return active.decode(errors="replace") if isinstance(active, bytes) else None
