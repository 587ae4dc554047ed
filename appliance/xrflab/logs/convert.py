"""Converting a log file to CSV, MAT v5, Parquet or rerun `.rrd`, in bounded memory.

Every converter walks `LogFile.iter_chunks` (CHUNK_ROWS records and reader.CHUNK_BYTES at a time,
the file's pages released after each), so a file of any
length converts with memory proportional to one chunk (MAT: to one column, since a MAT v5
variable is written whole). Output goes to a temporary file beside the target and is renamed
into place at the end: a download never sees a half-written file.

Column types, the same in every format: seq and cycle uint64, t_ns int64, bool as bool (CSV:
0/1), char as its unsigned byte value uint8 (reader.py says why), int int32, float float32,
double float64, long int int64. rerun stores every scalar as float64 (see _to_rrd).

The tabular formats (CSV, MAT, Parquet) of an xrflog file add one derived column after t_ns:
``t_s`` (float64), seconds from the run's start (``t_ns - start_mono_ns`` of the record's segment
header), so a plot or a spreadsheet needs no arithmetic on 19-digit nanoseconds. t_ns stays the
exact value; rerun has its own time axes.

The run's parameter changes (live tuning, docs/students/tuning.md: cycle, t, name, old, new, who;
the appliance's own log, not the loop's) travel inside each download when the caller passes them
(``changes``): CSV becomes a zip of two CSV files (the samples, unchanged, and the change table:
a spreadsheet or pandas opens each as the one table it is), MAT gets a struct variable
``param_changes``, Parquet the JSON table as the file's key-value metadata ``xrf.param_changes``,
and .rrd a text log entry per change at ``params/changes`` on both time lines. ``cycle`` is the
key to the samples: the first cycle that ran with the new value.
"""

from __future__ import annotations

import csv
import functools
import io
import json
import os
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

# The change table's columns and text, the CSV zip and MATLAB's names are shared with the light
# conversion child's CSV and MAT (plain.py, standard library only).
from .plain import (  # noqa: F401  (CHANGE_COLUMNS, changes_csv, csv_zip_names: this module's API too)
    CHANGE_COLUMNS,
    CHANGES_MAT,
    changes_csv,
    csv_zip_names,
    matlab_names,
    zip_csv,
)
from .reader import SECONDS_COLUMN, LogFile, Segment, open_log

# The .rrd's names and groups are shared with the light child's writer (rrdfile.py, standard library).
from .rrdfile import CHANGES_ENTITY, change_text, variable_groups  # noqa: F401  (this module's API too)

FORMATS = ("csv", "mat", "parquet", "rrd")
CHANGES_META = "xrf.param_changes"  # Parquet key-value metadata
SUFFIX = {"csv": ".csv", "mat": ".mat", "parquet": ".parquet", "rrd": ".rrd"}
CHUNK_ROWS = 1 << 17


def _plain(col: np.ndarray) -> np.ndarray:
    """A column in an output-friendly dtype: char bytes as uint8, everything else unchanged."""
    if col.dtype.kind == "S":
        return np.ascontiguousarray(col).view(np.uint8)
    return col


def table_columns(log: LogFile) -> list[str]:
    """The column names of the tabular formats: the log's columns with t_s after t_ns."""
    cols = list(log.columns)
    if "t_ns" in cols:
        cols.insert(cols.index("t_ns") + 1, SECONDS_COLUMN)
    return cols


def _seconds(seg: Segment, t_ns: np.ndarray) -> np.ndarray:
    # start_mono_ns is the loop's start on the same clock as t_ns; a header without it (a foreign
    # writer) counts from the segment's first record.
    start = seg.header.get("start_mono_ns")
    if not isinstance(start, int):
        start = int(seg.records["t_ns"][0]) if len(seg.records) else 0
    return (t_ns.astype(np.int64) - np.int64(start)).astype(np.float64) / 1e9


def with_seconds(seg: Segment, cols: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """`cols` (one chunk of `LogFile.iter_chunks`) with the t_s column after t_ns."""
    if "t_ns" not in cols:
        return cols
    out: dict[str, np.ndarray] = {}
    for name, col in cols.items():
        out[name] = col
        if name == "t_ns":
            out[SECONDS_COLUMN] = _seconds(seg, col)
    return out


# ---- CSV ------------------------------------------------------------------------------------


def _csv_table(cols: dict[str, np.ndarray]):
    import pyarrow as pa

    arrays = []
    for col in cols.values():
        col = _plain(col)
        if col.dtype == np.bool_:
            col = col.view(np.uint8)  # 0/1 reads back in MATLAB, spreadsheets and NumPy alike
        arrays.append(pa.array(np.ascontiguousarray(col)))
    return pa.Table.from_arrays(arrays, names=list(cols))


def iter_csv_chunks(path: str | Path, chunk_rows: int = CHUNK_ROWS, log: LogFile | None = None) -> Iterator[bytes]:
    """The CSV text of a log file, as byte chunks (header row first), for streaming responses.

    Numbers are written by Arrow's shortest round-trip formatting: every float64 and float32
    reads back to the identical value (`nan`, `inf`, `-inf` for the specials), integers in full.
    """
    import pyarrow.csv as pcsv

    log = log if log is not None else open_log(path)  # not `or`: a LogFile of no records is falsy
    sink = io.BytesIO()
    # The header row is ours (Arrow quotes every name); names are quoted only when they must be.
    head = io.StringIO()
    csv.writer(head, lineterminator="\n").writerow(table_columns(log))
    yield head.getvalue().encode()
    options = pcsv.WriteOptions(include_header=False, quoting_style="needed")
    writer = None
    for seg, cols in log.iter_chunks(chunk_rows):
        table = _csv_table(with_seconds(seg, cols))
        if writer is None:
            writer = pcsv.CSVWriter(sink, table.schema, write_options=options)
        writer.write_table(table)
        yield sink.getvalue()
        sink.seek(0)
        sink.truncate()
    if writer is not None:
        writer.close()
        rest = sink.getvalue()
        if rest:
            yield rest


def iter_csv_zip_chunks(
    path: str | Path,
    changes: list[dict[str, Any]],
    names: tuple[str, str],
    chunk_rows: int = CHUNK_ROWS,
    log: LogFile | None = None,
) -> Iterator[bytes]:
    """A zip of the samples' CSV (`iter_csv_chunks`, streamed: memory bounded by one chunk) and
    the change table's CSV, as byte chunks (plain.zip_csv)."""
    return zip_csv(iter_csv_chunks(path, chunk_rows, log=log), changes, names)


def _to_csv(log: LogFile, out: Path, chunk_rows: int, changes: list[dict[str, Any]] | None) -> None:
    if changes:
        run = changes[0].get("run", "")
        chunks = iter_csv_zip_chunks(log.path, changes, csv_zip_names(log.path.stem, run), chunk_rows, log=log)
    else:
        chunks = iter_csv_chunks(log.path, chunk_rows, log=log)
    with open(out, "wb") as f:
        for chunk in chunks:
            f.write(chunk)


# ---- MAT ------------------------------------------------------------------------------------


class _LazyColumns(Mapping[str, Any]):
    """A dict for scipy.io.savemat whose columns are built one at a time as savemat writes
    them (savemat only iterates items()), so the peak is one column, not the whole table."""

    def __init__(self, items: list[tuple[str, Callable[[], Any]]]) -> None:
        self._items = items

    def __getitem__(self, key: str) -> Any:
        for k, make in self._items:
            if k == key:
                return make()
        raise KeyError(key)

    def __iter__(self):
        return (k for k, _ in self._items)

    def __len__(self) -> int:
        return len(self._items)

    def items(self):  # a lazy mapping: each column is read when scipy asks for it
        for k, make in self._items:
            yield k, make()


def _column(log: LogFile, name: str) -> np.ndarray:
    if name == SECONDS_COLUMN:
        parts = [_seconds(seg, seg.column("t_ns")) for seg in log.segments]
    else:
        parts = [_plain(seg.column(name)) for seg in log.segments]
    if not parts:
        return np.empty(0)
    col = np.ascontiguousarray(parts[0]) if len(parts) == 1 else np.concatenate(parts)
    log.release_pages()  # a column is read across the whole file: its pages are done with
    return col


def _changes_struct(changes: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    """The change table as a MATLAB struct of columns (numbers as columns, text as cell arrays):
    `param_changes.name{k}` changed from `old(k)` to `new(k)` at cycle `cycle(k)`."""

    def text(key: str) -> np.ndarray:
        out = np.empty((len(changes), 1), dtype=object)
        for k, c in enumerate(changes):
            out[k, 0] = str(c.get(key, ""))
        return out

    def nums(key: str, dtype: Any) -> np.ndarray:
        return np.array([c.get(key, 0) for c in changes], dtype=dtype).reshape(-1, 1)

    return {
        "cycle": nums("cycle", np.uint64),
        "t": nums("t", np.float64),
        "name": text("name"),
        "old": nums("old", np.float64),
        "new": nums("new", np.float64),
        "who": text("who"),
    }


def _to_mat(log: LogFile, out: Path, chunk_rows: int, changes: list[dict[str, Any]] | None) -> None:
    from scipy.io import savemat

    log.check_uniform()
    columns = table_columns(log)
    header_names = columns[: len(columns) - len(log.variables)]
    var_names = matlab_names(
        [v.field for v in log.variables], reserved=tuple(header_names) + ("log_header", CHANGES_MAT)
    )
    items: list[tuple[str, Callable[[], Any]]] = [(n, functools.partial(_column, log, n)) for n in header_names]
    items += [(mname, functools.partial(_column, log, v.field)) for mname, v in zip(var_names, log.variables)]
    # The headers (cycle frequency, start time, identity; original names) as one JSON string.
    items.append(("log_header", lambda: json.dumps([s.header for s in log.segments])))
    if changes is not None:
        items.append((CHANGES_MAT, functools.partial(_changes_struct, changes)))
    with open(out, "wb") as f:
        savemat(f, _LazyColumns(items), format="5", oned_as="column", long_field_names=True, do_compression=False)


# ---- Parquet --------------------------------------------------------------------------------


def _to_parquet(log: LogFile, out: Path, chunk_rows: int, changes: list[dict[str, Any]] | None) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    writer = None
    kinds = {v.field: v.type_name for v in log.variables}
    try:
        for seg, cols in log.iter_chunks(chunk_rows):
            cols = with_seconds(seg, cols)
            arrays = [pa.array(np.ascontiguousarray(_plain(c))) for c in cols.values()]
            if writer is None:
                fields = [
                    pa.field(n, a.type, nullable=False, metadata={"xrf_type": kinds[n]} if n in kinds else None)
                    for n, a in zip(cols, arrays)
                ]
                meta = {"xrflog.headers": json.dumps([s.header for s in log.segments])}
                if changes is not None:
                    meta[CHANGES_META] = json.dumps(changes)
                schema = pa.schema(fields, metadata=meta)
                writer = pq.ParquetWriter(out, schema)
            # One row group per chunk: readers can stream the file back in the same steps.
            writer.write_table(pa.Table.from_arrays(arrays, schema=schema))
        if writer is None:  # no records: still a valid, typed, empty file
            empty = {
                c: np.empty(0, dtype=np.uint64 if c in ("seq", "cycle") else np.int64 if c == "t_ns" else np.float64)
                for c in table_columns(log)
            }
            empty.update({v.field: _plain(np.empty(0, dtype=v.dtype)) for v in log.variables})
            table = pa.table(empty)
            if changes is not None:
                table = table.replace_schema_metadata({CHANGES_META: json.dumps(changes)})
            pq.write_table(table, out)
    finally:
        if writer is not None:
            writer.close()


# ---- rerun ----------------------------------------------------------------------------------

RRD_FLUSH_CHUNKS = 2  # chunks (reader.CHUNK_BYTES of records each) between flushes of an .rrd


def entity_paths(names: list[str]) -> dict[str, str]:
    """name -> rerun entity path `log/<group>/<name>` (parts escaped for rerun's path syntax)."""
    import rerun as rr

    groups = variable_groups(names)
    return {n: f"log/{rr.escape_entity_path_part(groups[n])}/{rr.escape_entity_path_part(n)}" for n in names}


def rrd_blueprint(names: list[str], tuned: bool = False):
    """One TimeSeriesView per variable group, in a grid; a run with parameter changes gets a
    text log view of them too (the changes' entries are on the same time lines)."""
    import rerun as rr
    import rerun.blueprint as rrb

    groups = sorted(set(variable_groups(names).values()))
    views: list[Any] = [rrb.TimeSeriesView(origin=f"/log/{rr.escape_entity_path_part(g)}", name=g) for g in groups]
    if tuned:
        views.append(rrb.TextLogView(origin="/" + CHANGES_ENTITY, name="parameter changes"))
    return rrb.Blueprint(rrb.Grid(*views), collapse_panels=False)


def _to_rrd(log: LogFile, out: Path, chunk_rows: int, changes: list[dict[str, Any]] | None) -> None:
    """Timelines `cycle` (sequence; the record index for XRF2 files) and `time` (wall clock from
    t_ns; absent for XRF2 files). rerun's Scalars are float64: int64 values beyond 2**53 are
    rounded, every other type is exact."""
    import rerun as rr

    names = [v.field for v in log.variables]
    paths = entity_paths(names)
    rec = rr.RecordingStream("xrflab", recording_id=str(log.path.name))
    rec.save(out, default_blueprint=rrd_blueprint(names, tuned=bool(changes)))
    try:
        for n, (seg, cols) in enumerate(log.iter_chunks(chunk_rows), 1):
            cycle = cols.get("cycle", cols["seq"]).astype(np.int64)
            indexes = [rr.TimeColumn("cycle", sequence=cycle)]
            if "t_ns" in cols:
                indexes.append(rr.TimeColumn("time", timestamp=seg.wall_ns(cols["t_ns"]).view("datetime64[ns]")))
            for name in names:
                values = _plain(cols[name]).astype(np.float64)
                rec.send_columns(paths[name], indexes=indexes, columns=rr.Scalars.columns(scalars=values))
            # Written out every few chunks: the SDK's batcher and file writer otherwise held what
            # it had not written yet, growing with the log (a 600 000-record log: 344 -> 158 MB
            # RSS); a flush waits for the writer: after every chunk 145 MB but twice the time, every
            # 2nd 158 MB and ~1.3x, every 4th 179 MB and no slower (bench/README.md, session 10).
            if n % RRD_FLUSH_CHUNKS == 0:
                rec.flush()
        for c in changes or ():
            rec.set_time("cycle", sequence=int(c["cycle"]))
            rec.set_time("time", timestamp=float(c["t"]))
            rec.log(CHANGES_ENTITY, rr.TextLog(change_text(c), level="INFO"))
    finally:
        rec.flush()
        rec.disconnect()


# ---- entry point ----------------------------------------------------------------------------

_WRITERS: dict[str, Callable[[LogFile, Path, int, list[dict[str, Any]] | None], None]] = {
    "csv": _to_csv,
    "mat": _to_mat,
    "parquet": _to_parquet,
    "rrd": _to_rrd,
}


def convert(
    path: str | Path,
    fmt: str,
    out: str | Path | None = None,
    *,
    chunk_rows: int = CHUNK_ROWS,
    log: LogFile | None = None,
    changes: list[dict[str, Any]] | None = None,
) -> Path:
    """Write `path` (xrflog or XRF2 .bin) as `fmt` to `out` (default: beside it, with the
    format's suffix: `.zip` for CSV with parameter changes); returns the written path. `changes`:
    the run's parameter change table (rows of CHANGE_COLUMNS) to put inside. Raises
    LogFormatError for undecodable input."""
    if fmt not in _WRITERS:
        raise ValueError(f"unknown format {fmt!r}; formats: {', '.join(FORMATS)}")
    log = log if log is not None else open_log(path)  # not `or`: a LogFile of no records is falsy
    suffix = ".zip" if fmt == "csv" and changes else SUFFIX[fmt]
    target = Path(out) if out is not None else Path(path).with_suffix(suffix)
    tmp = target.with_name(f".{target.name}.{os.getpid()}.part")
    try:
        _WRITERS[fmt](log, tmp, chunk_rows, changes)
        os.replace(tmp, target)
    finally:
        if tmp.exists():
            tmp.unlink()
    return target
