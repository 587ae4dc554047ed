"""Log files: reading xrflog and XRF2 `.bin` files, converting them to CSV, MAT, Parquet, rrd.

    from xrflab.logs import open_log, convert, iter_csv_chunks
    log = open_log("probe_260101_120000.xrf")   # LogFile: .segments, .records, .lost, .skipped
    convert(log.path, "parquet")                # -> Path of the written file

Imported eagerly (NumPy, ~0.1 s): a lazy __getattr__ cannot work here because importing the
submodule `convert` rebinds the package attribute `convert` to the module. scipy, pyarrow and
rerun are imported only by the converter that needs them.

The appliance's side of a run's logging is not imported here: ``live`` (a run's logging, start to
finish), ``host_writer`` (ring -> file), ``log_channel`` (the shared memory's log ring and layout),
``record_file`` (whole records only), ``timing_series``, ``rerun_live`` (the live recording) and
``rerun_servers`` (rerun's child processes).
"""

# Every format besides xrflog registers itself with open_log when imported (xrf2bin: XRF2's .bin
# files); importing any module of this package runs this first, so open_log knows them all
# wherever it is called from.
from . import xrf2bin  # noqa: F401
from .convert import FORMATS, convert, iter_csv_chunks
from .reader import LogFile, LogFormatError, Segment, Variable, open_log

__all__ = ["FORMATS", "LogFile", "LogFormatError", "Segment", "Variable", "convert", "iter_csv_chunks", "open_log"]
