"""Log files: reading xrflog and XRF2 `.bin` files, converting them to CSV, MAT, Parquet, rrd.

    from xrflab.logs import open_log, convert, iter_csv_chunks
    log = open_log("probe_260101_120000.xrf")   # LogFile: .segments, .records, .lost, .skipped
    convert(log.path, "parquet")                # -> Path of the written file

Names are imported on first use: `xrf` imports xrflab.logs.cli for every call to build its
parser, and must not pay for NumPy then. scipy, pyarrow and rerun are imported only by the
converter that needs them.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "FORMATS": "convert", "convert": "convert", "iter_csv_chunks": "convert",
    "LogFile": "reader", "LogFormatError": "reader", "Segment": "reader", "Variable": "reader", "open_log": "reader",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
