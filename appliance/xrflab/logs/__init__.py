"""Log files: reading xrflog and XRF2 `.bin` files, converting them to CSV, MAT, Parquet, rrd.

    from xrflab.logs import open_log, iter_csv_chunks
    from xrflab.logs.convert import convert
    log = open_log("probe_260101_120000.xrf")   # LogFile: .segments, .records, .lost, .skipped
    convert(log.path, "parquet")                # -> Path of the written file

Nothing is imported here until it is asked for (PEP 562): the light conversion child
(``python -m xrflab.logs.convert_child``, logs/plain.py) runs this file first and must not load
NumPy (issue 30 item 4: a CSV or MAT child of ~12 MB instead of ~52). ``convert`` the function is
therefore taken from its module (``xrflab.logs.convert``, which is also the submodule's name: a
package attribute of that name would be the module once anything imported it). scipy, pyarrow and
rerun are imported only by the converter that needs them. Every format besides xrflog registers
itself with open_log when open_log first runs (reader.FORMAT_MODULES).

The appliance's side of a run's logging is not named here: ``live`` (a run's logging, start to
finish), ``host_writer`` (ring -> file), ``log_channel`` (the shared memory's log ring and layout),
``record_file`` (whole records only), ``timing_series``, ``rerun_live`` (the live recording),
``rerun_sender`` (its messages to the run's proxy, without the rerun SDK) and ``rerun_servers``
(rerun's child processes).
"""

from __future__ import annotations

import importlib
from typing import Any

_LAZY = {
    "FORMATS": "convert",
    "iter_csv_chunks": "convert",
    "LogFile": "reader",
    "LogFormatError": "layout",
    "Segment": "reader",
    "Variable": "reader",
    "open_log": "reader",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f".{module}", __name__), name)
